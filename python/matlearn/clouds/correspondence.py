"""Probabilistic correspondences between point clouds and the model surface (method.md section 7).

Surface points s_k are the surface vertices and, optionally, extra points embedded in the surface
triangles (edge midpoints, centroids) so that the correspondence sees the surface at a finer
spacing than the mesh. Candidate pairs (k, n) within `cutoff` sigma come from a KD tree (scipy
cKDTree, C); weights, residual r_k = sum_n p_kn (c_n - s_k) / sigma^2 and its Jacobian are
computed in C++ (`matlearn._core.observation`, cpp/observation/cloud_observation.*).

Relation to the marker path: for fixed weights, r_k = W_k (m_k - s_k) / sigma^2 with W_k the total
weight and m_k the weighted cloud mean, so a cloud observation is a weighted virtual marker at
m_k -- which is how tracked clouds become marker recordings (:mod:`matlearn.clouds.markers`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .. import _core

_ob = _core.observation


@dataclass
class SurfaceSamples:
    """Surface points embedded in a mesh: point k = sum_j weights[k, j] * x[index[k, j]].
    `vertex` (K,) is the vertex a point coincides with, or -1 for a point inside a triangle/edge."""

    index: np.ndarray  # (K, 3) int64
    weights: np.ndarray  # (K, 3)
    vertex: np.ndarray  # (K,)
    num_vertices: int

    @property
    def num_points(self) -> int:
        return len(self.index)

    def matrix(self) -> sp.csr_matrix:
        """E (K x n): S = E @ X."""
        K = self.num_points
        rows = np.repeat(np.arange(K), 3)
        return sp.csr_matrix((self.weights.ravel(), (rows, self.index.ravel())), shape=(K, self.num_vertices))

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Surface point positions for X (n, 3) or (T, n, 3)."""
        X = np.asarray(X, float)
        return np.einsum("kj,...kjd->...kd", self.weights, X[..., self.index, :])


def surface_samples(mesh, level: int = 1) -> SurfaceSamples:
    """Surface vertices (level 0), plus edge midpoints and triangle centroids (level 1)."""
    if level not in (0, 1):
        raise ValueError(f"level must be 0 or 1, got {level}")
    F = np.asarray(mesh.surface_faces, np.int64)
    n = int(mesh.num_vertices)
    sv = np.unique(F)
    idx = [np.stack([sv, sv, sv], axis=1)]
    w = [np.tile([1.0, 0.0, 0.0], (len(sv), 1))]
    vert = [sv]
    if level == 1:
        E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        E = np.unique(E, axis=0)
        idx += [np.stack([E[:, 0], E[:, 1], E[:, 1]], axis=1), F]
        w += [np.tile([0.5, 0.5, 0.0], (len(E), 1)), np.full((len(F), 3), 1.0 / 3.0)]
        vert += [np.full(len(E), -1), np.full(len(F), -1)]
    return SurfaceSamples(np.concatenate(idx), np.concatenate(w), np.concatenate(vert), n)


def find_pairs(S: np.ndarray, C: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """All (k, n) with |S[k] - C[n]| <= radius, as two int64 arrays sorted by k."""
    S, C = np.asarray(S, float).reshape(-1, 3), np.asarray(C, float).reshape(-1, 3)
    if len(S) == 0 or len(C) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    m = cKDTree(S).sparse_distance_matrix(cKDTree(C), radius, output_type="coo_matrix")
    order = np.lexsort((m.col, m.row))
    return m.row[order].astype(np.int64), m.col[order].astype(np.int64)


@dataclass
class Correspondence:
    """Correspondence of one frame: surface points S (K, 3), cloud C (N, 3) and the pairs."""

    S: np.ndarray
    C: np.ndarray
    pair_point: np.ndarray
    pair_cloud: np.ndarray
    sigma: float
    threshold: float

    def weights(self) -> np.ndarray:
        return _ob.cloud_weights(self.S, self.C, self.pair_point, self.pair_cloud, self.sigma, self.threshold)

    def residual(self) -> np.ndarray:
        """r (K, 3) = sum_n p_kn (c_n - s_k) / sigma^2 (method.md eq. of section 7, lambda = 1)."""
        return _ob.cloud_residual(self.S, self.C, self.pair_point, self.pair_cloud, self.sigma, self.threshold)

    def blocks(self, full: bool = False) -> np.ndarray:
        return _ob.cloud_residual_blocks(
            self.S, self.C, self.pair_point, self.pair_cloud, self.sigma, self.threshold, full
        )

    def targets(self) -> tuple[np.ndarray, np.ndarray]:
        """(weighted cloud mean (K, 3), NaN without support; total weight W (K,))."""
        return _ob.cloud_targets(self.S, self.C, self.pair_point, self.pair_cloud, self.sigma, self.threshold)


def correspond(S: np.ndarray, C: np.ndarray, sigma: float, cutoff: float = 3.0) -> Correspondence:
    """Pairs within `cutoff` sigma; weights below exp(-cutoff^2 / 2) are truncated to 0."""
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0 (m), got {sigma}")
    if not cutoff > 0:
        raise ValueError(f"cutoff must be > 0, got {cutoff}")
    pk, pn = find_pairs(S, C, cutoff * sigma)
    return Correspondence(np.asarray(S, float), np.asarray(C, float), pk, pn, float(sigma),
                          float(np.exp(-0.5 * cutoff**2)))


class CloudObservation:
    """The cloud observation term of one frame on the full vertex positions X (n, 3):
    residual C_z = lam * r(E X) (3K,) and Jacobian d C_z / d X (3K x 3n, sparse), with the
    correspondence re-estimated by :meth:`update` (call it as the fit proceeds)."""

    def __init__(self, samples: SurfaceSamples, cloud: np.ndarray, sigma: float, lam: float = 1.0,
                 cutoff: float = 3.0):
        self.samples, self.cloud = samples, np.asarray(cloud, float).reshape(-1, 3)
        self.sigma, self.lam, self.cutoff = float(sigma), float(lam), float(cutoff)
        self._E3 = sp.kron(samples.matrix(), sp.identity(3), format="csr")
        self.corr: Correspondence | None = None

    def update(self, X: np.ndarray) -> Correspondence:
        self.corr = correspond(self.samples.apply(X), self.cloud, self.sigma, self.cutoff)
        return self.corr

    def _at(self, X):
        c = self.corr
        if c is None:
            c = self.update(X)
        return Correspondence(self.samples.apply(X), c.C, c.pair_point, c.pair_cloud, c.sigma, c.threshold)

    def residual(self, X: np.ndarray) -> np.ndarray:
        """lam * r at X with the current pairs (weights recomputed at X), flattened (3K,)."""
        return self.lam * self._at(X).residual().ravel()

    def jacobian(self, X: np.ndarray, full: bool = False) -> sp.csr_matrix:
        """d residual / d X.ravel() (3K x 3n); full=False holds the weights fixed."""
        B = self._at(X).blocks(full)
        K = len(B)
        rows = np.repeat(np.arange(3 * K).reshape(K, 3), 3, axis=1).ravel()
        cols = np.tile(np.arange(3 * K).reshape(K, 3), (1, 3)).ravel()
        Jb = sp.csr_matrix((B.ravel(), (rows, cols)), shape=(3 * K, 3 * K))
        return (self.lam * Jb) @ self._E3


# ---------------------------------------------------------------------------- point-to-surface
@dataclass
class SurfaceMatch:
    """Each cloud point's closest point on the current surface: triangle `face` (N,), barycentric
    weights `bary` (N, 3) of its vertices `tri` (N, 3), offset c_n - p_n (N, 3) and Gaussian weight
    w_n = exp(-|c_n - p_n|^2 / (2 sigma^2)) (0 beyond `cutoff` sigma: outliers)."""

    tri: np.ndarray
    bary: np.ndarray
    offset: np.ndarray
    weight: np.ndarray

    def vertex_offsets(self, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-vertex weighted mean offset (n, 3) (0 where unsupported) and gathered weight W (n,):
        W_b = sum_n w_n bary_nb, offset_b = sum_n w_n bary_nb (c_n - p_n) / W_b."""
        wb = (self.weight[:, None] * self.bary).ravel()
        idx = self.tri.ravel()
        W = np.bincount(idx, wb, minlength=num_vertices)
        off = np.stack(
            [np.bincount(idx, wb * np.repeat(self.offset[:, d], 3), minlength=num_vertices) for d in range(3)],
            axis=1,
        )
        return off / np.maximum(W, 1e-300)[:, None], W


def match_surface(X: np.ndarray, faces: np.ndarray, cloud: np.ndarray, sigma: float,
                  cutoff: float = 3.0) -> SurfaceMatch:
    """Closest points of the cloud on the triangle surface (X (n, 3), faces (F, 3)), via open3d's
    ray-casting scene (BVH, C++); positions recomputed in float64 from the barycentrics."""
    import open3d as o3d

    if not sigma > 0:
        raise ValueError(f"sigma must be > 0 (m), got {sigma}")
    X = np.asarray(X, float)
    faces = np.asarray(faces, np.int64)
    cloud = np.asarray(cloud, float).reshape(-1, 3)
    if len(cloud) == 0:
        z = np.zeros((0, 3))
        return SurfaceMatch(np.zeros((0, 3), np.int64), z, z, np.zeros(0))
    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(o3d.core.Tensor(X.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    ans = sc.compute_closest_points(o3d.core.Tensor(cloud.astype(np.float32)))
    f = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    tri = faces[f]
    p = np.einsum("nj,njd->nd", bary, X[tri])
    off = cloud - p
    d2 = np.einsum("nd,nd->n", off, off)
    w = np.exp(-0.5 * d2 / sigma**2)
    w[d2 > (cutoff * sigma) ** 2] = 0.0
    return SurfaceMatch(tri, bary, off, w)
