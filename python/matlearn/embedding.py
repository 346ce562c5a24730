"""Embedding rest-space points (markers, drive points) in a tet mesh.

A point inside the mesh gets the barycentric coordinates of its tet; a point outside (a marker
slightly off a curved surface that the mesh only approximates) is attached to the closest point
of the closest surface triangle, with barycentric weights on that triangle's 3 vertices (the 4th
vertex of its tet gets weight 0). Positions then follow linearly: p = S @ X.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

_INSIDE_TOL = 1e-9  # barycentric slack for points on faces / edges


@dataclass
class Embedding:
    """tet (K,): tet index; vertices (K, 4) = mesh.tets[tet]; bary (K, 4) weights summing to 1;
    inside (K,): point lies in its tet; distance (K,): rest distance to the mesh (0 inside)."""

    tet: np.ndarray
    vertices: np.ndarray
    bary: np.ndarray
    inside: np.ndarray
    distance: np.ndarray

    @property
    def num_points(self) -> int:
        return len(self.tet)

    def matrix(self, num_vertices: int) -> sp.csr_matrix:
        """S (K x num_vertices), so that points = S @ X for vertex positions X (n, 3)."""
        K = self.num_points
        rows = np.repeat(np.arange(K), 4)
        return sp.csr_matrix(
            (self.bary.ravel(), (rows, self.vertices.ravel())), shape=(K, num_vertices)
        )

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Point positions from vertex positions: X (n, 3) -> (K, 3), X (T, n, 3) -> (T, K, 3)."""
        X = np.asarray(X)
        if X.ndim == 2:
            return np.einsum("kj,kjd->kd", self.bary, X[self.vertices])
        if X.ndim != 3 or X.shape[-1] != 3:
            raise ValueError(f"X: expected shape (n, 3) or (T, n, 3), got {X.shape}")
        T, n = X.shape[:2]
        # One sparse product over all frames: (K x n) @ (n x 3T), no (T, K, 4, 3) temporary.
        Y = self.matrix(n) @ np.ascontiguousarray(X.transpose(1, 0, 2)).reshape(n, 3 * T)
        return np.ascontiguousarray(Y.reshape(-1, T, 3).transpose(1, 0, 2))

    def nearest_vertices(self) -> np.ndarray:
        """(K,) the vertex carrying the largest weight of each point."""
        return self.vertices[np.arange(self.num_points), np.argmax(self.bary, axis=1)]


def _tet_bary(V, tets, tet_idx, P):
    """Barycentric coordinates (k, 4) of points P (k, 3) in tets tet_idx (k,)."""
    v = V[tets[tet_idx]]  # (k, 4, 3)
    D = np.transpose(v[:, 1:] - v[:, :1], (0, 2, 1))  # (k, 3, 3) columns = edges
    lam = np.linalg.solve(D, (P - v[:, 0])[..., None])[..., 0]
    return np.concatenate([1 - lam.sum(axis=1, keepdims=True), lam], axis=1)


def _closest_on_triangles(P, A, B, C):
    """Closest points on triangles (A, B, C) (k, 3) to P (k, 3); returns barycentric (k, 3)
    (Ericson, Real-Time Collision Detection 5.1.5, vectorised)."""
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = P - B
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = P - C
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    k = len(P)
    out = np.zeros((k, 3))
    done = np.zeros(k, bool)

    def put(mask, w):
        nonlocal done
        m = mask & ~done
        out[m] = w[m] if w.ndim == 2 else w
        done |= m

    eps = 1e-300
    put((d1 <= 0) & (d2 <= 0), np.array([1.0, 0, 0]))
    put((d3 >= 0) & (d4 <= d3), np.array([0, 1.0, 0]))
    t = d1 / np.where(d1 - d3 == 0, eps, d1 - d3)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - t, t, 0 * t], 1))
    put((d6 >= 0) & (d5 <= d6), np.array([0, 0, 1.0]))
    t = d2 / np.where(d2 - d6 == 0, eps, d2 - d6)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - t, 0 * t, t], 1))
    den = (d4 - d3) + (d5 - d6)
    t = (d4 - d3) / np.where(den == 0, eps, den)
    put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([0 * t, 1 - t, t], 1))
    s = va + vb + vc
    s = np.where(s == 0, eps, s)
    put(np.ones(k, bool), np.stack([1 - (vb + vc) / s, vb / s, vc / s], 1))
    return out


def _face_owner(tets: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each surface face: its tet and the local index (0..3) of each face vertex in it."""
    local = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    tf = np.sort(tets[:, local].reshape(-1, 3), axis=1)
    # Vectorised matching via a structured view of the sorted triples.
    dt = np.dtype([("a", np.int64), ("b", np.int64), ("c", np.int64)])
    tf_v = np.ascontiguousarray(tf.astype(np.int64)).view(dt).ravel()
    sf_v = np.ascontiguousarray(np.sort(faces, axis=1).astype(np.int64)).view(dt).ravel()
    order = np.argsort(tf_v)
    pos = np.searchsorted(tf_v[order], sf_v)
    pos = np.clip(pos, 0, len(order) - 1)
    hit = order[pos]
    if np.any(tf_v[hit] != sf_v):
        raise ValueError("surface faces do not match any tet face (corrupt mesh)")
    tet = hit // 4
    tv = tets[tet]  # (F, 4)
    loc = np.argmax(tv[:, None, :] == faces[:, :, None], axis=2)  # (F, 3)
    return tet, loc


def _search_tets(V, tets, tree, P, idx, k, tet, bary) -> None:
    """For points idx: the first of their k nearest-centroid tets that contains them (in place)."""
    if len(idx) == 0 or k == 0:
        return
    _, cand = tree.query(P[idx], k=k)
    cand = cand.reshape(len(idx), k)
    for j in range(k):  # loop over candidate rank, vectorised over points
        left = np.flatnonzero(tet[idx] < 0)
        if len(left) == 0:
            break
        pts = idx[left]
        b = _tet_bary(V, tets, cand[left, j], P[pts])
        ok = b.min(axis=1) >= -_INSIDE_TOL
        tet[pts[ok]] = cand[left[ok], j]
        bary[pts[ok]] = b[ok]


def _closest_surface(V, faces, P, k: int = 32):
    """Closest surface triangle of each point among the k with the nearest centroids:
    (face index (p,), barycentric weights (p, 3), distance (p,))."""
    k = min(len(faces), k)
    _, fcand = cKDTree(V[faces].mean(axis=1)).query(P, k=k)
    fcand = fcand.reshape(len(P), k)
    best_d = np.full(len(P), np.inf)
    best_f = np.zeros(len(P), np.int64)
    best_w = np.zeros((len(P), 3))
    for j in range(k):
        f = fcand[:, j]
        A, B, C = (V[faces[f, i]] for i in range(3))
        w = _closest_on_triangles(P, A, B, C)
        q = w[:, :1] * A + w[:, 1:2] * B + w[:, 2:] * C
        d = np.linalg.norm(P - q, axis=1)
        better = d < best_d
        best_d[better], best_f[better], best_w[better] = d[better], f[better], w[better]
    return best_f, best_w, best_d


def embed_points(mesh, points, candidates: int = 16) -> Embedding:
    """Embed rest-space points (K, 3) in `mesh` (a TetMesh or anything with .vertices, .tets,
    .surface_faces)."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points: expected shape (K, 3), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError("points: contains NaN or Inf")
    V = np.asarray(mesh.vertices, float)
    tets = np.asarray(mesh.tets, np.int64)
    K, m = len(P), len(tets)
    tet = -np.ones(K, np.int64)
    bary = np.zeros((K, 4))
    if K == 0:
        return Embedding(tet, np.zeros((0, 4), np.int64), bary, np.zeros(0, bool), np.zeros(0))

    # 1) Containing tet among the nearest tet centroids.
    centroids = V[tets].mean(axis=1)
    tree = cKDTree(centroids)
    _search_tets(V, tets, tree, P, np.arange(K), min(candidates, m), tet, bary)

    # 2) The rest: closest surface triangle. A point whose closest point lies inside a face, on
    # the face's outer side, is outside the mesh; the others get a wide tet search first.
    faces = np.asarray(mesh.surface_faces, np.int64)
    distance = np.zeros(K)
    inside = np.ones(K, bool)
    rest = np.flatnonzero(tet < 0)
    if len(rest):
        f, w, d = _closest_surface(V, faces, P[rest])
        A, B, C = (V[faces[f, i]] for i in range(3))
        normal = np.cross(B - A, C - A)
        q = w[:, :1] * A + w[:, 1:2] * B + w[:, 2:] * C
        clearly_out = (w.min(axis=1) > 1e-9) & (((P[rest] - q) * normal).sum(axis=1) > 0)
        unsure = rest[~clearly_out]
        _search_tets(V, tets, tree, P, unsure, min(8 * candidates, m), tet, bary)
        still = tet[rest] < 0
        inside[rest[still]] = False
        out, f, w, d = rest[still], f[still], w[still], d[still]
        if len(out):
            ftet, floc = _face_owner(tets, faces)
            tet[out] = ftet[f]
            b = np.zeros((len(out), 4))
            np.put_along_axis(b, floc[f], w, axis=1)
            bary[out] = b
            distance[out] = d
    return Embedding(tet, tets[tet], bary, inside, distance)
