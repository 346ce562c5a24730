"""Mesh builders and loaders: meshio round trips (.vtu, .msh), TetGen .node/.ele, surfaces
(.obj) through TetGen, and builder volumes against analytic values."""
import numpy as np
import pytest

from matlearn import meshes


def same_mesh(a, b):
    np.testing.assert_allclose(a.vertices, b.vertices, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_allclose(a.rest_volumes, b.rest_volumes, rtol=1e-12)


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk"])
def test_meshio_round_trip(tmp_path, suffix):
    mesh = meshes.bar(0.2, 0.04, 0.03, cells=(5, 2, 2))
    path = tmp_path / f"bar{suffix}"
    meshes.save_mesh(mesh, path)
    same_mesh(mesh, meshes.load_mesh(path))


def test_tetgen_node_ele(tmp_path):
    mesh = meshes.bar(cells=(3, 1, 1))
    V, T = mesh.vertices, mesh.tets
    node = ["# comment", f"{len(V)} 3 0 0"] + [f"{i + 1} {x:.17g} {y:.17g} {z:.17g}" for i, (x, y, z) in enumerate(V)]
    ele = [f"{len(T)} 4 0"] + [f"{e + 1} " + " ".join(str(i + 1) for i in t) for e, t in enumerate(T)]
    (tmp_path / "m.node").write_text("\n".join(node) + "\n")
    (tmp_path / "m.ele").write_text("\n".join(ele) + "\n")
    same_mesh(mesh, meshes.load_mesh(tmp_path / "m.ele"))


def test_surface_obj_through_tetgen(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=(0.2, 0.1, 0.05))
    path = tmp_path / "box.obj"
    box.export(path)
    mesh = meshes.load_mesh(path, max_volume=1e-5)
    np.testing.assert_allclose(mesh.rest_volumes.sum(), 0.2 * 0.1 * 0.05, rtol=1e-9)
    assert mesh.num_tets > 50  # the volume bound refined it
    assert mesh.rest_volumes.max() <= 1e-5 * (1 + 1e-9)
    # The boundary of the tet mesh is the box surface: its area matches.
    F = mesh.surface_faces
    V = mesh.vertices
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    np.testing.assert_allclose(area, box.area, rtol=1e-9)


def test_surface_faces_point_outward():
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(4, 2, 2))
    V, F = mesh.vertices, mesh.surface_faces
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    c = V[F].mean(1) - V.mean(0)
    assert (np.einsum("ij,ij->i", n, c) > 0).all()
    # Divergence theorem: the oriented surface encloses the volume.
    vol = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6
    np.testing.assert_allclose(vol, 0.2 * 0.04 * 0.04, rtol=1e-12)


def test_bar_volume_and_cells():
    mesh = meshes.bar(0.3, 0.05, 0.02, cells=(6, 2, 1))
    assert mesh.num_tets == 6 * 6 * 2 * 1
    np.testing.assert_allclose(mesh.rest_volumes.sum(), 0.3 * 0.05 * 0.02, rtol=1e-12)
    assert (mesh.rest_volumes > 0).all()
    m = meshes.bar_with_tets(0.2, 0.04, 0.04, target_tets=1000)
    assert 600 < m.num_tets < 1500


def test_sphere_volume():
    r = 0.05
    mesh = meshes.sphere(radius=r, subdivisions=3)
    # The icosphere (642 vertices) inscribes the sphere: ~1 % less volume.
    np.testing.assert_allclose(mesh.rest_volumes.sum(), 4 / 3 * np.pi * r**3, rtol=0.03)
    assert mesh.rest_volumes.sum() < 4 / 3 * np.pi * r**3


def test_capsule_volume():
    r, length = 0.02, 0.1
    mesh = meshes.capsule(radius=r, length=length)
    exact = np.pi * r**2 * length + 4 / 3 * np.pi * r**3
    np.testing.assert_allclose(mesh.rest_volumes.sum(), exact, rtol=0.05)
    ext = np.ptp(mesh.vertices, axis=0)
    np.testing.assert_allclose(ext[0], length + 2 * r, rtol=0.02)  # along +x


def test_layered_bar_labels():
    mesh, layer = meshes.layered_bar(cells=(4, 2, 4))
    assert layer.shape == (mesh.num_tets,)
    c = mesh.vertices[mesh.tets].mean(1)
    np.testing.assert_array_equal(layer, (c[:, 2] > 0).astype(int))
    np.testing.assert_allclose(mesh.rest_volumes[layer == 1].sum(), mesh.rest_volumes.sum() / 2, rtol=1e-12)


def test_lumped_mass():
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(4, 2, 2))
    rho = np.linspace(900, 1200, mesh.num_tets)
    m = mesh.lumped_mass(rho)
    np.testing.assert_allclose(m.sum(), (rho * mesh.rest_volumes).sum(), rtol=1e-12)
    with pytest.raises(ValueError, match="density"):
        mesh.lumped_mass(rho[:-1])
