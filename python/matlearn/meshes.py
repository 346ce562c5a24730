"""Tet meshes: procedural builders, file loading (meshio / trimesh + TetGen), validation.

All lengths in metres. Every builder returns a :class:`TetMesh` (the C++ mesh with rest data).
"""
from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from . import _core

TetMesh = _core.fem.TetMesh

# Six tets per hexahedral cell (Kuhn / Freudenthal split): conforming across neighbouring cells.
_KUHN = np.array(
    [[0, 1, 3, 7], [0, 1, 7, 5], [0, 5, 7, 4], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7]]
)


def _orient(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap two indices of every negatively oriented tet."""
    d = vertices[tets[:, 1:]] - vertices[tets[:, :1]]
    neg = np.linalg.det(d) < 0
    tets = tets.copy()
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    return tets


def unique_edges(T: np.ndarray) -> np.ndarray:
    """The sorted unique vertex pairs (E, 2) of the tets' edges."""
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    E = np.sort(T[:, pairs].reshape(-1, 2), axis=1)
    return np.unique(E, axis=0)


def refine_tets(V: np.ndarray, T: np.ndarray):
    """Regular 1-to-8 refinement: edge midpoints become vertices (appended after V in the order
    of the sorted unique edge list), each tet splits into 4 corner tets and 4 octahedron tets."""
    E = unique_edges(T)
    n = len(V)
    Vn = np.vstack([V, 0.5 * (V[E[:, 0]] + V[E[:, 1]])])
    key = E[:, 0].astype(np.int64) * n + E[:, 1]
    order = np.argsort(key)

    def mid(a, b):
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return n + order[np.searchsorted(key[order], lo.astype(np.int64) * n + hi)]

    a, b, c, d = T.T
    ab, ac, ad, bc, bd, cd = mid(a, b), mid(a, c), mid(a, d), mid(b, c), mid(b, d), mid(c, d)
    kids = [
        (a, ab, ac, ad), (ab, b, bc, bd), (ac, bc, c, cd), (ad, bd, cd, d),
        (ab, ac, ad, bd), (ab, ac, bc, bd), (ac, ad, bd, cd), (ac, bc, bd, cd),
    ]
    Tn = np.stack([np.stack(k, axis=1) for k in kids], axis=1).reshape(-1, 4)
    return Vn, _orient(Vn, Tn)


def folded_tets(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Indices of tets that overlap a neighbour: across an interior face (shared by two tets) the
    two opposite vertices must lie on opposite sides of the face's plane; where they lie on the
    same side the mesh folds over itself (an inverted element that a per-tet re-orientation
    hides). Faces shared by more than two tets (a non-manifold mesh) count too."""
    V = np.asarray(vertices, float)
    T = np.asarray(tets, np.int64)
    local = np.array([[1, 2, 3, 0], [0, 2, 3, 1], [0, 1, 3, 2], [0, 1, 2, 3]])
    faces = T[:, local[:, :3]].reshape(-1, 3)
    opp = T[:, local[:, 3]].reshape(-1)
    owner = np.repeat(np.arange(len(T)), 4)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    bad = set(owner[counts[inv] > 2].tolist())
    pair = np.flatnonzero(counts[inv] == 2)
    order = pair[np.argsort(inv[pair], kind="stable")]
    a, b = order[0::2], order[1::2]
    k = key[a]  # the same vertex order for both sides
    n = np.cross(V[k[:, 1]] - V[k[:, 0]], V[k[:, 2]] - V[k[:, 0]])
    sa = np.einsum("ij,ij->i", n, V[opp[a]] - V[k[:, 0]])
    sb = np.einsum("ij,ij->i", n, V[opp[b]] - V[k[:, 0]])
    same = sa * sb > 0
    bad.update(owner[a[same]].tolist())
    bad.update(owner[b[same]].tolist())
    return np.array(sorted(bad), np.int64)


def _indices_checked(n: int, tets, path, base: int = 0) -> np.ndarray:
    """`tets` (int64), or a ValueError naming the file when they are not 4 indices each or refer
    to a vertex outside the file's `n` (reported in the file's numbering, from `base`)."""
    T = np.asarray(tets, np.int64)
    if T.ndim != 2 or T.shape[1] != 4 or len(T) == 0:
        raise ValueError(f"{path}: expected tets with 4 vertex indices each, got shape {T.shape}")
    out = np.flatnonzero(((T < 0) | (T >= n)).any(axis=1))
    if len(out):
        e = int(out[0])
        raise ValueError(f"{path}: {len(out)} tets refer to vertices that do not exist (the mesh has {n}, "
                         f"numbered from {base}), e.g. tet {e + base} with vertices {(T[e] + base).tolist()}")
    return T


def _checked(vertices, tets, path, base: int = 0) -> np.ndarray:
    """`tets` of a mesh file oriented to positive volume, or a ValueError naming the file and the
    first bad tets: a vertex index outside the file's vertices (in the file's own numbering,
    which starts at `base`), a vertex repeated within a tet, a zero volume, or a fold."""
    V = np.asarray(vertices, float)
    T = _indices_checked(len(V), tets, path, base)
    S = np.sort(T, axis=1)
    rep = np.flatnonzero((S[:, 1:] == S[:, :-1]).any(axis=1))
    if len(rep):
        raise ValueError(f"{path}: {len(rep)} tets repeat a vertex, e.g. tet {int(rep[0]) + base} with vertices "
                         f"{(T[rep[0]] + base).tolist()}")
    scale = float(np.linalg.norm(np.ptp(V, axis=0)))
    vol = np.abs(np.linalg.det(V[T[:, 1:]] - V[T[:, :1]])) / 6.0
    flat = np.flatnonzero(vol <= 1e-14 * scale**3)  # TetMesh's own bound (cpp/fem/tet_mesh.cpp)
    if len(flat):
        raise ValueError(f"{path}: {len(flat)} degenerate (zero-volume) tets, e.g. tets "
                         f"{(flat[:8] + base).tolist()}; fix or re-mesh it")
    tets = _orient(V, T)
    bad = folded_tets(V, tets)
    if len(bad):
        raise ValueError(f"{path}: {len(bad)} tets overlap a neighbour (the mesh folds over itself: "
                         f"inverted elements), e.g. tets {bad[:8].tolist()}; fix or re-mesh it")
    return tets


def grid_tets(shape: tuple[int, int, int], size: tuple[float, float, float], origin=(0.0, 0.0, 0.0)):
    """Vertices and tets of a box of `shape` cells (nx, ny, nz) and `size` (m)."""
    nx, ny, nz = shape
    if min(shape) < 1:
        raise ValueError(f"grid shape must be positive, got {shape}")
    xs = [np.linspace(o, o + s, n + 1) for o, s, n in zip(origin, size, shape)]
    X, Y, Z = np.meshgrid(*xs, indexing="ij")
    vertices = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange((nx + 1) * (ny + 1) * (nz + 1)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    corners = np.stack(
        [idx[i + a, j + b, k + c] for c in (0, 1) for b in (0, 1) for a in (0, 1)], axis=1
    )  # corner bit order: a + 2b + 4c
    tets = corners[:, _KUHN].reshape(-1, 4)
    return vertices, _orient(vertices, tets)


def bar(length=0.2, width=0.04, height=0.04, cells=(10, 2, 2)) -> TetMesh:
    """A box-shaped bar along +x starting at x = 0, centred on the x axis."""
    V, T = grid_tets(cells, (length, width, height), origin=(0.0, -width / 2, -height / 2))
    return TetMesh(V, T)


def bar_with_tets(length=0.2, width=0.04, height=0.04, target_tets=1000) -> TetMesh:
    """A bar whose cell counts are chosen (keeping cells near-cubic) for about `target_tets`."""
    h = (length * width * height / (target_tets / 6.0)) ** (1.0 / 3.0)
    cells = tuple(max(1, int(round(d / h))) for d in (length, width, height))
    return bar(length, width, height, cells)


def layered_bar(length=0.2, width=0.04, height=0.04, cells=(10, 2, 4)):
    """A bar plus a per-tet layer label (0 bottom half, 1 top half, split in z)."""
    mesh = bar(length, width, height, cells)
    centroids = mesh.vertices[mesh.tets].mean(axis=1)
    return mesh, (centroids[:, 2] > 0).astype(np.int64)


def sphere(radius=0.05, max_volume=None, min_ratio=1.5, subdivisions=3) -> TetMesh:
    """A tetrahedralised sphere centred at the origin (icosphere surface + TetGen)."""
    import trimesh

    surf = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    if max_volume is None:
        max_volume = (radius / 4) ** 3
    return tetrahedralize(surf.vertices, surf.faces, max_volume=max_volume, min_ratio=min_ratio)


def capsule(radius=0.02, length=0.1, max_volume=None, min_ratio=1.5) -> TetMesh:
    """A capsule along +x (trimesh surface + TetGen)."""
    import trimesh

    surf = trimesh.creation.capsule(height=length, radius=radius, count=[12, 12])
    surf.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    if max_volume is None:
        max_volume = (radius / 3) ** 3
    return tetrahedralize(surf.vertices, surf.faces, max_volume=max_volume, min_ratio=min_ratio)


def tetrahedralize(vertices, faces, max_volume: float = 0.0, min_ratio: float = 0.0) -> TetMesh:
    """Tetrahedralise a closed surface with TetGen (volume bound in m^3, radius-edge bound)."""
    V, T = _core.mesh.tetrahedralize(
        np.asarray(vertices, float), np.asarray(faces, np.int64), max_volume or 0.0, min_ratio or 0.0
    )
    return TetMesh(V, T)


SURFACE_SUFFIXES = {".obj", ".ply", ".stl", ".off"}
# a surface's volume bound asking for more tets than this is refused rather than meshed for hours
# (a max_volume written in mm^3 or cm^3 for a body in metres)
MAX_TETGEN_TETS = 5e6
# the smallest radius-edge bound a surface is meshed with (load_mesh; the core's kMinRadiusEdgeRatio
# refuses less for every caller)
MIN_RADIUS_EDGE_RATIO = 1.1
VOLUME_SUFFIXES = {".msh", ".vtk", ".vtu", ".node", ".ele", ".mesh"}


def load_mesh(path, max_volume: float | None = None, min_ratio: float | None = None) -> TetMesh:
    """Load a tet mesh (.msh/.vtk/.vtu/TetGen .node+.ele) or tetrahedralise a closed surface
    (.obj/.ply/.stl/.off) with TetGen. Tets of a volume mesh are re-oriented to positive volume
    (files from other tools may use the opposite vertex order); quadratic tets keep their corners."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix in SURFACE_SUFFIXES:
        import trimesh

        surf = trimesh.load(path, force="mesh", process=True)
        if len(surf.faces) == 0:
            raise ValueError(f"{path}: no triangles found")
        if not surf.is_watertight:
            raise ValueError(
                f"{path}: surface is not closed (watertight); TetGen needs a closed, manifold surface"
            )
        if max_volume is None:
            ext = np.ptp(surf.vertices, axis=0)
            max_volume = float(np.prod(ext)) / 2000.0
        elif not max_volume > 0:
            raise ValueError(f"{path}: max_volume must be a positive volume (m^3), got {max_volume}")
        if min_ratio is not None and not min_ratio >= MIN_RADIUS_EDGE_RATIO:
            raise ValueError(f"{path}: min_ratio must be at least {MIN_RADIUS_EDGE_RATIO} (TetGen's radius-edge "
                             f"bound: below it its refinement may never finish), got {min_ratio}")
        count = abs(float(surf.volume)) / max_volume  # TetGen makes more tets than this, not fewer
        if count > MAX_TETGEN_TETS:
            raise ValueError(f"{path}: max_volume = {max_volume:g} m^3 would make at least {count:.3g} tets of this "
                             f"{abs(float(surf.volume)):.3g} m^3 body (more than {MAX_TETGEN_TETS:.0e}); are the surface "
                             "and max_volume both in metres?")
        return tetrahedralize(surf.vertices, surf.faces, max_volume, 1.5 if min_ratio is None else min_ratio)
    if suffix in (".node", ".ele"):
        return _load_tetgen(path.with_suffix(""))
    if suffix in VOLUME_SUFFIXES:
        import meshio

        with contextlib.redirect_stdout(io.StringIO()):  # meshio's gmsh reader prints a blank line
            m = meshio.read(path)
        # quadratic tets (gmsh/VTK second order): their first four nodes are the corners
        tets = [c.data[:, :4] for c in m.cells if c.type in ("tetra", "tetra10")]
        if not tets:
            raise ValueError(f"{path}: no tetrahedra found (cell types: {[c.type for c in m.cells]})")
        V = np.asarray(m.points, float)
        if V.shape[1] == 2:
            raise ValueError(f"{path}: 2-D points, expected 3-D")
        T = _indices_checked(len(V), np.concatenate(tets), path)
        used = np.unique(T)
        if len(used) != len(V):  # drop points not used by any tet (e.g. gmsh geometry points)
            remap = -np.ones(len(V), np.int64)
            remap[used] = np.arange(len(used))
            V, T = V[used], remap[T]
        return TetMesh(V, _checked(V, T, path))  # tools differ in their orientation convention
    raise ValueError(
        f"{path}: unsupported mesh format '{suffix}' (volume: {sorted(VOLUME_SUFFIXES)}, "
        f"surface: {sorted(SURFACE_SUFFIXES)})"
    )


def _load_tetgen(stem: Path) -> TetMesh:
    node, ele = stem.with_suffix(".node"), stem.with_suffix(".ele")
    for p in (node, ele):
        if not p.exists():
            raise FileNotFoundError(f"TetGen file not found: {p}")

    def rows(p):
        lines = [ln.split("#")[0].split() for ln in p.read_text().splitlines()]
        return [ln for ln in lines if ln]

    nl = rows(node)
    n = int(nl[0][0])
    pts = np.array([[float(v) for v in ln[1:4]] for ln in nl[1 : n + 1]])
    first = int(nl[1][0])
    el = rows(ele)
    m = int(el[0][0])
    tets = np.array([[int(v) for v in ln[1:5]] for ln in el[1 : m + 1]]) - first
    return TetMesh(pts, _checked(pts, tets, ele, base=first))


def save_mesh(mesh: TetMesh, path, cell_data: dict | None = None) -> None:
    """Write a tet mesh with meshio (format from the suffix), with optional per-tet data."""
    import meshio

    cd = {k: [np.asarray(v)] for k, v in (cell_data or {}).items()}
    meshio.write(path, meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)], cell_data=cd))


def object_size(mesh: TetMesh) -> float:
    """Rest bounding-box diagonal (m): the length error percentages refer to."""
    return float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))


def surface_vertices(mesh: TetMesh) -> np.ndarray:
    """Indices of the vertices on the boundary surface."""
    return np.unique(mesh.surface_faces)
