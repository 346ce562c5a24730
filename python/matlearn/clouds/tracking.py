"""Physics-based tracking of the model mesh through a point-cloud sequence (the paper's Fig. 3),
giving the initial trajectory for learning and per-frame virtual markers.

Per recording frame j (time t_j), a predict-correct filter on the scene model:

1. *predict*: simulate the scene model (backward Euler at the scene's time step, clamp,
   gravity, driven vertices) from the tracked state at t_{j-1} to t_j;
2. *correct*: match every cloud point to its closest point on the predicted surface (open3d
   BVH), weight the match by the Gaussian w_n = exp(-d_n^2 / (2 sigma^2)), truncated beyond
   `cutoff` sigma (outliers), and solve for the displacement d of the free vertices minimising
       d^T K d + kappa sum_n w_n (nrm_n . (p_n(x + d) - c_n))^2
   (point-to-plane distances regularised by the elastic energy of the change, K the model's
   PSD-projected tangent). Positions move by beta d, velocities by gamma beta d / dt. The
   correction repeats `em_iterations` times with the matches re-estimated (EM-style).

A frame without points (dropped) is a pure prediction; occluded parts follow through K and the
dynamics. The per-vertex *support* (matched weight relative to a fully visible vertex) says
which vertices the cloud actually saw in a frame.

Why this data term and not the vertex-centred Gaussian means of method.md section 7 (which
:mod:`.correspondence` implements for the space-time observation): on a mesh whose edges are
much longer than sigma, a vertex-centred weighted mean is biased inwards by O(sigma) at convex
edges and, used as a position target, shrinks the mesh step after step (measured on a 10x2x2
bar: 0.75 % of the object size at the true pose, drifting to > 2 % over 5 corrections, against
0.07 % for point-to-surface matches). Full point-to-point targets also pin supported vertices
tangentially (a face sliding in its own plane looks unmoved), hence point-to-plane. And why
not attraction forces inside the time step: forcing a vertex to reach a noisy target within a
frame turns target noise into velocity noise of order noise / dt (tried: 2 % error where the
nominal model alone is at 0.3 %).

A recording not at rest initially starts from a pose fitted to frame 0 by the same correction
(beta = 1) with sigma annealed from 5 % of the object size down to the tracking sigma, with
velocity 0 (the paper's release from a held pose).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..progress import ProgressBar
from ..recording import Recording
from ..replay import drive_vertices, interpolate_frames
from .correspondence import match_surface


@dataclass
class TrackOptions:
    """sigma: robust kernel width of the matches (m); None = max(cloud_sigma, a quarter of the
    median surface edge). cutoff: matches beyond cutoff sigma are outliers. beta: position gain
    (0, 1] of the correction; gamma: velocity gain (0 = positions only). em_iterations:
    corrections per frame. data_weight: data stiffness relative to the elastic one.
    init_iterations: corrections fitting frame 0 when not at rest. min_support: support at which
    a vertex counts as seen (markers)."""

    sigma: float | None = None
    cutoff: float = 3.0
    beta: float = 0.7
    gamma: float = 0.3
    em_iterations: int = 2
    data_weight: float = 0.1
    init_iterations: int = 8
    min_support: float = 0.25
    max_newton: int = 4

    def __post_init__(self):
        if not 0 < self.beta <= 1:
            raise ValueError(f"beta must lie in (0, 1], got {self.beta}")
        if self.gamma < 0:
            raise ValueError(f"gamma must be >= 0, got {self.gamma}")
        if self.em_iterations < 1 or self.init_iterations < 0:
            raise ValueError("em_iterations must be >= 1 and init_iterations >= 0")
        if not self.data_weight > 0:
            raise ValueError(f"data_weight must be > 0, got {self.data_weight}")
        if self.sigma is not None and not self.sigma > 0:
            raise ValueError(f"sigma must be > 0 (m), got {self.sigma}")


@dataclass
class TrackResult:
    """times (T,); X, V (T, n, 3) tracked positions/velocities at the recording times;
    support (T, n) per-vertex support (0 unseen, ~1 fully seen); per-frame fit statistics in
    `residual` (lists over frames: rms_m / mean_m distance of inlier points to the tracked
    surface, inlier_fraction, points); sigma used."""

    times: np.ndarray
    X: np.ndarray
    V: np.ndarray
    support: np.ndarray
    sigma: float
    residual: dict = field(default_factory=dict)


def default_sigma(mesh, cloud_sigma: float | None) -> float:
    """max(scanner sigma, a quarter of the median surface edge length)."""
    F = np.asarray(mesh.surface_faces)
    V = np.asarray(mesh.vertices)
    edge = float(np.median(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1)))
    return float(max(cloud_sigma or 0.0, 0.25 * edge))


def cloud_density(cloud: np.ndarray) -> float:
    """Points per m^2 of scanned surface: 1 / a^2, a the median nearest-neighbour spacing."""
    from scipy.spatial import cKDTree

    if len(cloud) < 2:
        return 0.0
    a = float(np.median(cKDTree(cloud).query(cloud, k=2)[0][:, 1]))
    return 1.0 / max(a, 1e-12) ** 2


class _Corrector:
    """Point-to-surface matches -> elastically regularised point-to-plane correction."""

    def __init__(self, scene, model, opts: TrackOptions):
        self.opts, self.model = opts, model
        n = scene.mesh.num_vertices
        self.faces = np.asarray(scene.mesh.surface_faces, np.int64)
        V = np.asarray(scene.mesh.vertices, float)
        e1 = V[self.faces[:, 1]] - V[self.faces[:, 0]]
        e2 = V[self.faces[:, 2]] - V[self.faces[:, 0]]
        fa = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
        self.area = np.bincount(self.faces.ravel(), np.repeat(fa / 3.0, 3), minlength=n)
        self.free = np.ones(n, bool)
        self.free[np.asarray(scene.fixed, np.int64)] = False

    def extend(self, x, v, idx, disp) -> np.ndarray:
        """Displacement (n, 3) that moves vertices `idx` by `disp` and the other free vertices
        elastically (K_ff d_f = -K_fi disp)."""
        d = np.zeros_like(x)
        d[idx] = disp
        free = self.free.copy()
        free[idx] = False
        if free.any():
            K = self.model.stiffness(x, v, project_psd=True).tocsr()
            f3, i3 = np.repeat(free, 3), np.zeros(3 * len(x), bool)
            i3[np.repeat(np.isin(np.arange(len(x)), idx), 3)] = True
            Kff = K[f3][:, f3]
            shift = 1e-12 * float(np.median(Kff.diagonal()))
            rhs = -(K[f3][:, i3] @ d[np.isin(np.arange(len(x)), idx)].ravel())
            d[free] = spla.spsolve((Kff + shift * sp.identity(Kff.shape[0])).tocsc(), rhs).reshape(-1, 3)
        return d

    def support(self, x: np.ndarray, cloud: np.ndarray, sigma: float) -> np.ndarray:
        """Per-vertex support (n,): gathered match weight W_b relative to what a fully visible
        vertex gathers (its surface area share x the cloud's density), so 1 ~ fully seen."""
        m = match_surface(x, self.faces, cloud, sigma, self.opts.cutoff)
        _, W = m.vertex_offsets(len(x))
        return W / np.maximum(self.area * cloud_density(cloud), 1e-300)

    def correction(self, x, v, cloud, sigma: float, beta: float, held=()) -> np.ndarray:
        """Displacement (n, 3) minimising, over the free vertices,
            d^T K d + kappa sum_n w_n (nrm_n . (p_n(x + d) - c_n))^2,
        i.e. point-to-plane distances of the matched cloud points (normal of the matched
        triangle) regularised by the elastic energy of the change (K: the model's PSD-projected
        tangent at x). The data constrain each surface patch only along its normal; tangential
        motion comes from elasticity and the prediction. kappa = data_weight x the median
        diagonal of K over the median matched weight of a supported vertex. Scaled by beta;
        clamped and `held` vertices do not move."""
        n = len(x)
        m = match_surface(x, self.faces, cloud, sigma, self.opts.cutoff)
        keep = m.weight > 0
        d = np.zeros_like(x)
        if not keep.any():
            return d
        tri, bary, off, w = m.tri[keep], m.bary[keep], m.offset[keep], m.weight[keep]
        P = x[tri]
        nrm = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        b = np.einsum("nd,nd->n", nrm, off)
        N = len(b)
        rows = np.repeat(np.arange(N), 9)
        cols = (3 * tri[:, :, None] + np.arange(3)[None, None, :]).reshape(N, 9).ravel()
        vals = (bary[:, :, None] * nrm[:, None, :]).reshape(N, 9).ravel()
        A = sp.csr_matrix((vals, (rows, cols)), shape=(N, 3 * n))
        free = self.free.copy()
        held = np.asarray(held, np.int64)
        if len(held):
            free[held] = False
        f3 = np.repeat(free, 3)
        K = self.model.stiffness(x, v, project_psd=True).tocsr()[f3][:, f3]
        Af = A[:, f3]
        Wd = sp.diags(w)
        _, Wb = m.vertex_offsets(n)
        kdiag = float(np.median(K.diagonal()))
        wsup = float(np.median(Wb[Wb > 0])) if np.any(Wb > 0) else 1.0
        kappa = self.opts.data_weight * kdiag / max(wsup, 1e-300)
        H = (K + kappa * (Af.T @ Wd @ Af)).tocsc()
        g = kappa * (Af.T @ (w * b))
        H = H + (1e-12 * kdiag) * sp.identity(H.shape[0], format="csc")
        d[free] = beta * spla.spsolve(H, g).reshape(-1, 3)
        return d


def _surface_distance_stats(X: np.ndarray, faces: np.ndarray, cloud: np.ndarray, inlier: float) -> dict:
    if len(cloud) == 0:
        return {"rms_m": float("nan"), "mean_m": float("nan"), "inlier_fraction": float("nan"), "points": 0}
    import open3d as o3d

    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(o3d.core.Tensor(X.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    d = sc.compute_distance(o3d.core.Tensor(cloud.astype(np.float32))).numpy().astype(np.float64)
    ok = d <= inlier
    di = d[ok]
    return {
        "rms_m": float(np.sqrt(np.mean(di**2))) if len(di) else float("nan"),
        "mean_m": float(np.mean(di)) if len(di) else float("nan"),
        "inlier_fraction": float(ok.mean()),
        "points": int(len(cloud)),
    }


def fit_initial_pose(scene, model, rec: Recording, opts: TrackOptions, sigma: float | None = None) -> np.ndarray:
    """Fit the model to frame 0's cloud (see the module docstring). Returns x0 (n, 3)."""
    sigma = sigma or default_sigma(scene.mesh, rec.cloud_sigma)
    n = scene.mesh.num_vertices
    x = np.array(scene.mesh.vertices, float)
    cloud = rec.cloud(0)
    if len(cloud) == 0:
        raise ValueError("tracking: frame 0 has no cloud points and the recording is not at rest")
    corr = _Corrector(scene, model, opts)
    didx, dtargets = drive_vertices(scene, rec)
    zero = np.zeros((n, 3))
    if len(didx):  # move the driven vertices first, elastically
        x = x + corr.extend(x, zero, didx, dtargets[0] - x[didx])
    s_hi = max(0.05 * scene.object_size, sigma)
    its = max(opts.init_iterations, 2)
    for i in range(its):
        s = s_hi * (sigma / s_hi) ** min(1.0, i / (its - 2))
        x = x + corr.correction(x, zero, cloud, s, 1.0, held=didx)
    return x


def track(scene, rec: Recording, opts: TrackOptions | None = None, model=None,
          progress: bool = False, state=None) -> TrackResult:
    """Track the scene's model mesh through the clouds of `rec` (see the module docstring).
    state: optional known initial (x0, v0); default rest (at_rest_initially) or the pose fitted
    to frame 0 with zero velocity."""
    opts = opts or TrackOptions()
    if not rec.has_clouds:
        raise ValueError("tracking needs a recording with point clouds (cloud_points/cloud_offsets)")
    model = model if model is not None else scene.model()
    mesh = scene.mesh
    n = mesh.num_vertices
    sigma = opts.sigma or default_sigma(mesh, rec.cloud_sigma)
    h = scene.time_step
    integ = scene.integrator(model, max_newton=opts.max_newton)
    corr = _Corrector(scene, model, opts)
    faces = np.asarray(mesh.surface_faces)
    didx, dtargets = drive_vertices(scene, rec)

    v0 = np.zeros((n, 3))
    if state is not None:
        x0, v0 = (np.array(a, float).reshape(n, 3) for a in state)
    elif rec.at_rest_initially:
        x0 = np.array(mesh.vertices, float)
    else:
        x0 = fit_initial_pose(scene, model, rec, opts, sigma)
    if len(didx):
        integ.set_prescribed(didx)
        x0[didx] = dtargets[0]
    integ.set_state(x0, v0)

    T = rec.num_frames
    X = np.zeros((T, n, 3))
    Vel = np.zeros((T, n, 3))
    X[0], Vel[0] = x0, v0
    support = np.zeros((T, n))
    stats = []
    zero = np.zeros((n, 3))

    def record(j):
        cloud = rec.cloud(j)
        if len(cloud):
            support[j] = corr.support(X[j], cloud, sigma)
        stats.append(_surface_distance_stats(X[j], faces, cloud, opts.cutoff * sigma))

    record(0)
    bar = ProgressBar("track", enabled=progress)
    for j in range(1, T):
        dt = rec.times[j] - rec.times[j - 1]
        m = max(1, int(round(dt / h)))
        if len(didx):
            t_sub = rec.times[j - 1] + dt * np.arange(1, m + 1) / m
            drive_t = interpolate_frames(rec.times, dtargets, t_sub)
            for s in range(m):
                integ.step(zero, drive_t[s])
        else:
            integ.simulate(m, zero, m)
        x, v = np.array(integ.x), np.array(integ.v)
        cloud = rec.cloud(j)
        if len(cloud):
            total = np.zeros_like(x)
            for _ in range(opts.em_iterations):
                d = corr.correction(x, v, cloud, sigma, opts.beta, held=didx)
                x = x + d
                total += d
            v = v + opts.gamma * total / dt
            integ.set_state(x, v)
        X[j], Vel[j] = x, v
        record(j)
        bar(j, T - 1)
    bar.close()
    residual = {k: [s[k] for s in stats] for k in ("rms_m", "mean_m", "inlier_fraction", "points")}
    return TrackResult(np.asarray(rec.times), X, Vel, support, sigma, residual)


def tracked_markers(scene, rec: Recording, result: TrackResult | None = None,
                    opts: TrackOptions | None = None) -> Recording:
    """A marker recording from a cloud recording, so that `matlearn learn` runs on clouds through
    the marker path: one marker per surface vertex (marker_rest = its rest position), at its
    tracked position in the frames where its support reaches opts.min_support (NaN elsewhere:
    occluded, dropped frames). Drive points and at_rest_initially are kept; clouds dropped."""
    opts = opts or TrackOptions()
    result = result or track(scene, rec, opts)
    sv = np.unique(np.asarray(scene.mesh.surface_faces))
    pos = result.X[:, sv].copy()
    seen = result.support[:, sv] >= opts.min_support
    if not seen.any():
        raise ValueError("tracked_markers: no surface vertex is supported by the clouds in any frame")
    pos[~seen] = np.nan
    rest = np.asarray(scene.mesh.vertices)[sv]
    return Recording(rec.times, rest, pos, at_rest_initially=rec.at_rest_initially,
                     drive_rest=rec.drive_rest, drive=rec.drive)


def refresh_markers(scene, rec: Recording, sim_times: np.ndarray, X: np.ndarray, model=None,
                    opts: TrackOptions | None = None) -> Recording:
    """Re-estimate the correspondences of a cloud recording at a new trajectory (method.md
    section 7: "re-estimating p as the space-time solve proceeds"): the trajectory X
    (S, n, 3) at `sim_times` is interpolated to each recording frame, corrected towards
    that frame's cloud (em_iterations of the tracker's point-to-plane correction, beta = 1) and returned as a
    tracked-marker recording like :func:`tracked_markers`. A learning loop calls this between
    outer iterations with the current space-time trajectory so that the virtual markers follow
    the improving model instead of staying at the nominal tracker's estimate."""
    opts = opts or TrackOptions()
    model = model if model is not None else scene.model()
    n = scene.mesh.num_vertices
    X = np.asarray(X, float)
    if X.ndim != 3 or X.shape[1:] != (n, 3) or len(X) != len(sim_times):
        raise ValueError(f"X: expected shape ({len(sim_times)}, {n}, 3), got {X.shape}")
    sigma = opts.sigma or default_sigma(scene.mesh, rec.cloud_sigma)
    corr = _Corrector(scene, model, opts)
    didx, _ = drive_vertices(scene, rec)
    Xf = interpolate_frames(np.asarray(sim_times, float), X, rec.times)
    support = np.zeros((rec.num_frames, n))
    zero = np.zeros((n, 3))
    for j in range(rec.num_frames):
        cloud = rec.cloud(j)
        if len(cloud) == 0:
            continue
        for _ in range(opts.em_iterations):
            Xf[j] = Xf[j] + corr.correction(Xf[j], zero, cloud, sigma, 1.0, held=didx)
        support[j] = corr.support(Xf[j], cloud, sigma)
    res = TrackResult(np.asarray(rec.times), Xf, np.zeros_like(Xf), support, sigma, {})
    return tracked_markers(scene, rec, res, opts)
