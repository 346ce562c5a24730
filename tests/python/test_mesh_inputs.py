"""Valid inputs made by other tools than matlearn's own writers (found with
bench/diagnosis_independent.py and its probes): they must load as the same body."""
from __future__ import annotations

import meshio
import numpy as np
import pytest

from matlearn import meshes


def _box():
    V, T = meshes.grid_tets((3, 2, 1), (0.06, 0.04, 0.02))
    return V, T


def _flip(T, which):
    T = T.copy()
    T[which, 1], T[which, 2] = T[which, 2].copy(), T[which, 1].copy()
    return T


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
@pytest.mark.parametrize("which", ["all", "half"])
def test_volume_mesh_with_other_orientation_convention(tmp_path, suffix, which):
    """A tet mesh whose tets are (all or some) negatively oriented is the same body: it loads,
    with the reference rest volumes (it used to raise 'inverted tets')."""
    V, T = _box()
    sel = np.ones(len(T), bool) if which == "all" else (np.arange(len(T)) % 2 == 0)
    path = tmp_path / f"m{suffix}"
    kw = {"file_format": "gmsh22", "binary": False} if suffix == ".msh" else {}
    meshio.write(path, meshio.Mesh(V, [("tetra", _flip(T, sel))]), **kw)
    m = meshes.load_mesh(path)
    ref = meshes.TetMesh(V, T)
    assert m.num_tets == ref.num_tets
    np.testing.assert_allclose(np.sort(m.rest_volumes), np.sort(ref.rest_volumes), rtol=1e-12)
    assert np.all(np.asarray(m.rest_volumes) > 0)


def test_tetgen_files_with_other_orientation(tmp_path):
    V, T = _box()
    T = _flip(T, np.ones(len(T), bool))
    (tmp_path / "b.node").write_text(
        f"{len(V)} 3 0 0\n" + "".join(f"{i + 1} {x} {y} {z}\n" for i, (x, y, z) in enumerate(V)))
    (tmp_path / "b.ele").write_text(
        f"{len(T)} 4 0\n" + "".join(f"{i + 1} " + " ".join(str(v + 1) for v in t) + "\n" for i, t in enumerate(T)))
    m = meshes.load_mesh(tmp_path / "b.ele")
    assert m.num_tets == len(T)
    np.testing.assert_allclose(np.sum(m.rest_volumes), 0.06 * 0.04 * 0.02, rtol=1e-12)


def test_gmsh_second_order_mesh_with_boundary_triangles(tmp_path):
    """gmsh output: boundary triangles plus quadratic tets (tetra10). The corners make the body;
    the mid-edge nodes, used by no linear tet, are dropped (it used to raise 'no tetrahedra')."""
    V, T = _box()
    edges = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [2, 3], [1, 3]])  # gmsh tetra10 edge order
    key = {}
    P = [*V]
    T10 = np.zeros((len(T), 10), np.int64)
    for e, t in enumerate(T):
        T10[e, :4] = t
        for j, (a, b) in enumerate(edges):
            k = tuple(sorted((t[a], t[b])))
            if k not in key:
                key[k] = len(P)
                P.append(0.5 * (V[k[0]] + V[k[1]]))
            T10[e, 4 + j] = key[k]
    F = meshes.TetMesh(V, T).surface_faces
    path = tmp_path / "q.msh"
    meshio.write(path, meshio.Mesh(np.array(P), [("triangle", np.asarray(F)), ("tetra10", T10)]),
                 file_format="gmsh22", binary=False)
    m = meshes.load_mesh(path)
    assert m.num_vertices == len(V) and m.num_tets == len(T)
    np.testing.assert_allclose(np.sort(m.vertices, axis=0), np.sort(V, axis=0))
    np.testing.assert_allclose(np.sum(m.rest_volumes), 0.06 * 0.04 * 0.02, rtol=1e-12)


@pytest.mark.parametrize("suffix", [".msh", ".vtu"])
def test_a_folded_mesh_is_refused(tmp_path, suffix):
    """A vertex pushed through its neighbours makes tets overlap; re-orienting each negative tet
    (as done for files of another orientation convention) would hide that, so loading names them."""
    m = meshes.bar(0.1, 0.02, 0.02, (8, 2, 2))
    V, T = np.asarray(m.vertices).copy(), np.asarray(m.tets)
    assert len(meshes.folded_tets(V, T)) == 0
    c = int(np.argmin(np.linalg.norm(V - V.mean(axis=0), axis=1)))  # an interior vertex
    V[c, 0] += 0.03  # 2.4 cells along the bar
    meshio.write(tmp_path / f"folded{suffix}", meshio.Mesh(V, [("tetra", T)]))
    with pytest.raises(ValueError, match=r"tets overlap a neighbour \(the mesh folds over itself"):
        meshes.load_mesh(tmp_path / f"folded{suffix}")
    bad = meshes.folded_tets(V, meshes._orient(V, T))
    touching = np.flatnonzero(np.any(T == c, axis=1))
    assert len(bad) and set(bad) <= set(touching) | set(np.flatnonzero(np.any(np.isin(T, T[touching]), axis=1)))


def _tetgen(tmp_path, V, T, base=1):
    (tmp_path / "b.node").write_text(
        f"{len(V)} 3 0 0\n" + "".join(f"{i + base} {x} {y} {z}\n" for i, (x, y, z) in enumerate(V)))
    (tmp_path / "b.ele").write_text(
        f"{len(T)} 4 0\n" + "".join(f"{i + base} " + " ".join(str(v + base) for v in t) + "\n"
                                    for i, t in enumerate(T)))
    return tmp_path / "b.ele"


@pytest.mark.parametrize("base", [0, 1])
def test_bad_tets_are_named_with_the_file_and_its_numbering(tmp_path, base):
    """A .ele index beyond the .node count raised numpy's IndexError; a repeated vertex was called
    a fold and a flat tet was named without its file."""
    V, T = _box()
    bad = T.copy()
    bad[5, 2] = len(V)  # one past the last vertex
    with pytest.raises(ValueError, match=rf"b.ele: 1 tets refer to vertices that do not exist \(the mesh has "
                                         rf"{len(V)}, numbered from {base}\), e.g. tet {5 + base} "):
        meshes.load_mesh(_tetgen(tmp_path, V, bad, base))
    bad = T.copy()
    bad[3, 1] = bad[3, 0]
    with pytest.raises(ValueError, match=rf"b.ele: 1 tets repeat a vertex, e.g. tet {3 + base} "):
        meshes.load_mesh(_tetgen(tmp_path, V, bad, base))
    flat = np.vstack([V, 0.5 * (V[T[0, 0]] + V[T[0, 1]])])  # a tet on an edge's midpoint: no volume
    with pytest.raises(ValueError, match=rf"b.ele: 1 degenerate \(zero-volume\) tets, e.g. tets \[{len(T) + base}\]"):
        meshes.load_mesh(_tetgen(tmp_path, flat, np.vstack([T, [T[0, 0], T[0, 1], len(V), T[0, 2]]]), base))
    assert meshes.load_mesh(_tetgen(tmp_path, V, T, base)).num_tets == len(T)  # the good file loads


def test_a_volume_mesh_index_out_of_range_is_named(tmp_path):
    V, T = _box()
    T = T.copy()
    T[0, 0] = len(V) + 3
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(V, [("tetra", T)]))
    with pytest.raises(ValueError, match=r"m.vtu: 1 tets refer to vertices that do not exist"):
        meshes.load_mesh(tmp_path / "m.vtu")
