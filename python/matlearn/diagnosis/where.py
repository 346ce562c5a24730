"""Where the nominal model is wrong: the equation-of-motion residual (control forces) of a
constrained simulation that follows the markers, mapped to elements, regions, frames and
regimes (method.md section 9, "Where").

Control forces. The vertices nearest the seen markers (and the driven ones) are prescribed to
follow the recording; the rest of the body obeys the nominal model. The control force is what
the model lacks to produce that motion, `fc = M a - f(x, v) - M g` (backward Euler), non-zero on
the prescribed vertices. When the learning step's space-time control forces are available they
can be passed instead (`ResidualField.from_forces`).

Stress residual. Element principal stress residuals dp solve `min |B dp - fc|^2 + eps |dp|^2`
(B the force map) per sampled frame: the element-level picture of the control forces.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse.linalg as spla

from .. import replay
from ..learning.initial import fill_marker_gaps


@dataclass
class ResidualField:
    times: np.ndarray  # (F,) sampled frame times (s)
    forces: np.ndarray  # (F, n, 3) control forces (N)
    dp: np.ndarray  # (F, m, 3) principal stress residual (Pa)
    Fh: np.ndarray  # (F, m, 3)
    Fhdot: np.ndarray  # (F, m, 3)
    velocity: np.ndarray  # (F, n, 3)
    volumes: np.ndarray  # (m,)


def constrained_residual(problem, model, rec, max_frames: int = 30) -> ResidualField:
    """Control forces of the nominal model along a recording (see module docstring)."""
    scene = problem.scene
    emb = problem.embedding(rec)
    h = scene.time_step
    sim_t = replay.simulation_times(scene, rec)
    near = emb.nearest_vertices()
    fixed = np.zeros(scene.mesh.num_vertices, bool)
    fixed[scene.fixed] = True
    V = np.asarray(scene.mesh.vertices)
    # marker displacement -> nearest vertex (averaged); unseen frames filled as in the learning
    # step (from the frame's seen markers, short gaps in time), markers never seen dropped
    mk, seen_markers = fill_marker_gaps(rec.times, rec.markers, rec.marker_rest)
    near = near[seen_markers]
    disp = mk - rec.marker_rest[seen_markers][None]
    uniq, inv = np.unique(near, return_inverse=True)
    vd = np.zeros((len(rec.times), len(uniq), 3))
    np.add.at(vd, (slice(None), inv), disp)
    vd /= np.bincount(inv)[None, :, None]
    keep = ~fixed[uniq]
    idx, vd = uniq[keep], vd[:, keep]
    didx, dtar = replay.drive_vertices(scene, rec)
    targets = V[idx][None] + vd
    if len(didx):
        m2 = ~np.isin(idx, didx)
        idx = np.concatenate([idx[m2], didx])
        targets = np.concatenate([targets[:, m2], dtar], axis=1)
    T_at = replay.interpolate_frames(rec.times, targets, sim_t)
    x0, v0 = replay.initial_state(scene, model, rec, emb)
    x0 = np.array(x0)
    x0[idx] = T_at[0]
    steps = len(sim_t) - 1
    # the whole constrained run in one C++ call; only a few sampled frames are analysed below
    X, Vel = replay.follow_targets(scene, model, idx, T_at, x0, v0, max_newton=problem.fast_newton)
    frames = np.unique(np.linspace(1, steps, min(max_frames, steps)).astype(int))
    M = np.asarray(model.vertex_mass)[:, None]
    g = np.asarray(scene.gravity)[None]
    B = None
    F = []
    DP, FH, FHD = [], [], []
    for i in frames:  # a few sampled frames, each one C++ evaluation
        f = np.asarray(model.forces(X[i], Vel[i]))
        fc = M * (Vel[i] - Vel[i - 1]) / h - f - M * g
        fc[fixed] = 0.0
        F.append(fc)
        B = model.force_map(X[i])
        dp = spla.lsqr(B, fc.ravel(), damp=1e-6 * _scale(B), atol=1e-8, btol=1e-8, iter_lim=400)[0]
        Fh, Fhd, _, _ = model.principal_kinematics(X[i], Vel[i])
        DP.append(dp.reshape(-1, 3))
        FH.append(np.asarray(Fh))
        FHD.append(np.asarray(Fhd))
    return ResidualField(sim_t[frames], np.array(F), np.array(DP), np.array(FH), np.array(FHD),
                         np.array([Vel[i] for i in frames]),
                         np.asarray(scene.mesh.rest_volumes))


def spacetime_residual(problem, model, rec, max_frames: int = 30, modes: int = 24,
                       lam: float = 1.0, iterations: int = 4) -> ResidualField:
    """Control forces from the learning step's sparse reduced space-time optimisation
    (matlearn.learning, method.md section 5): full-space forces on every vertex, not only on
    the marker-nearest ones, so the element map is sharper."""
    from ..learning.initial import initial_trajectory
    from ..learning.pod import pod_basis
    from ..learning.spacetime import build_problem, constrained_vertices, solve_spacetime

    scene = problem.scene
    emb = problem.embedding(rec)
    _, X0, _ = initial_trajectory(scene, model, rec, emb)
    _, (sim_t, Xs, _) = problem.predict(model, rec, fast=True, full=True)
    cons, _, _ = constrained_vertices(scene, rec)
    phi = pod_basis([Xs, X0], np.asarray(scene.mesh.vertices, float), cons, modes)
    setup = build_problem(scene, model, rec, phi, lam, emb)
    out = solve_spacetime(setup, X0, iterations=iterations)
    fc = np.asarray(out["control_forces"])  # frames 2..N
    X, Vel = out["X"], out["V"]
    idx = np.unique(np.linspace(0, len(fc) - 1, min(max_frames, len(fc))).astype(int))
    DP, FH, FHD = [], [], []
    for i in idx:  # a few sampled frames, each one C++ evaluation
        B = model.force_map(X[i + 2])
        dp = spla.lsqr(B, fc[i].ravel(), damp=1e-6 * _scale(B), atol=1e-8, btol=1e-8, iter_lim=400)[0]
        Fh, Fhd, _, _ = model.principal_kinematics(X[i + 2], Vel[i + 2])
        DP.append(dp.reshape(-1, 3))
        FH.append(np.asarray(Fh))
        FHD.append(np.asarray(Fhd))
    return ResidualField(setup.times[idx + 2], fc[idx], np.array(DP), np.array(FH), np.array(FHD),
                         Vel[idx + 2], np.asarray(scene.mesh.rest_volumes))


def residual_field(problem, model, rec, source: str = "spacetime") -> tuple[ResidualField, str]:
    """Control forces from `source` ("spacetime" or "constrained"); space-time falls back to the
    constrained simulation if it fails. Returns (field, source used)."""
    if source not in ("spacetime", "constrained"):
        raise ValueError(f"residual source must be 'spacetime' or 'constrained', got {source!r}")
    if source == "spacetime":
        try:
            return spacetime_residual(problem, model, rec), "spacetime"
        except (ImportError, RuntimeError, ValueError, AttributeError):
            pass
    return constrained_residual(problem, model, rec), "constrained"


def _scale(B) -> float:
    return float(np.sqrt(abs(B).power(2).sum() / max(B.shape[1], 1)))


def merge(fields: list[ResidualField]) -> ResidualField:
    cat = lambda k: np.concatenate([getattr(f, k) for f in fields])  # noqa: E731
    return ResidualField(cat("times"), cat("forces"), cat("dp"), cat("Fh"), cat("Fhdot"),
                         cat("velocity"), fields[0].volumes)


def element_shares(field: ResidualField) -> np.ndarray:
    """Per-element share of the residual (sums to 1): the stress-residual work rate
    W_e |dp_e . Fhdot_e| plus the stress-residual magnitude, each normalised, averaged."""
    W = field.volumes
    power = (W[None] * np.abs(np.einsum("fmi,fmi->fm", field.dp, field.Fhdot))).sum(axis=0)
    mag = (W[None] * np.linalg.norm(field.dp, axis=2)).sum(axis=0)
    s = 0.5 * power / max(power.sum(), 1e-300) + 0.5 * mag / max(mag.sum(), 1e-300)
    return s / max(s.sum(), 1e-300)


def share_by_time(field: ResidualField, rec_times=None, bins: int = 10) -> list:
    """[[t, share], ...]: fraction of the control-force power per time bin."""
    p = np.abs(np.einsum("fni,fni->f", field.forces, field.velocity)) + 1e-30
    p = p + np.linalg.norm(field.forces, axis=(1, 2)) * 1e-12
    t = field.times
    edges = np.linspace(t.min(), t.max() + 1e-12, bins + 1)
    which = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, bins - 1)
    share = np.bincount(which, weights=p, minlength=bins)
    share = share / share.sum()
    return [[float(edges[i]), float(share[i])] for i in range(bins)]


def regime_split(field: ResidualField) -> dict:
    """Tension vs compression: residual stress magnitude where the principal stretch is > 1 vs
    < 1. Elastic vs dissipative: per element and principal direction, the residual regressed on
    (s - 1) and the stretch rate; the energies of the two fitted parts."""
    W = field.volumes[None, :, None]
    a = np.abs(field.dp) * W
    e = field.Fh - 1.0
    ten = float(a[e > 0].sum())
    com = float(a[e <= 0].sum())
    # per element-direction 2-variable least squares over frames (vectorised normal equations)
    r, x1, x2 = field.dp, e, field.Fhdot
    s11, s22, s12 = (x1 * x1).sum(0), (x2 * x2).sum(0), (x1 * x2).sum(0)
    b1, b2 = (x1 * r).sum(0), (x2 * r).sum(0)
    det = s11 * s22 - s12**2
    ok = det > 1e-12 * (s11 * s22 + 1e-300)
    ca = np.where(ok, (s22 * b1 - s12 * b2) / np.where(ok, det, 1), 0.0)
    cb = np.where(ok, (s11 * b2 - s12 * b1) / np.where(ok, det, 1), 0.0)
    Wv = field.volumes[:, None]
    el = float((Wv * ca**2 * s11).sum())
    di = float((Wv * cb**2 * s22).sum())
    t1 = ten + com if ten + com > 0 else 1.0
    t2 = el + di if el + di > 0 else 1.0
    return {"tension": ten / t1, "compression": com / t1, "elastic": el / t2, "dissipative": di / t2}


def find_regions(mesh, shares: np.ndarray, max_regions: int = 5, mass: float = 0.8, seed: int = 0):
    """Cluster the elements carrying the top `mass` fraction of the residual by their centroids;
    the number of clusters maximises the silhouette (1 when no split has silhouette > 0.5).
    Returns [{"elements", "share", "centroid"}], largest share first."""
    from sklearn.cluster import KMeans
    from sklearn.metrics import silhouette_score

    C = np.asarray(mesh.vertices)[np.asarray(mesh.tets)].mean(axis=1)
    order = np.argsort(-shares)
    cum = np.cumsum(shares[order])
    heavy = order[: max(1, int(np.searchsorted(cum, mass)) + 1)]
    labels = np.zeros(len(heavy), int)
    if len(heavy) >= 6:
        best = (0.5, None)
        for k in range(2, min(max_regions, len(heavy) - 1) + 1):
            km = KMeans(k, n_init=4, random_state=seed).fit(C[heavy], sample_weight=shares[heavy])
            if len(set(km.labels_)) < 2:
                continue
            sil = silhouette_score(C[heavy], km.labels_)
            if sil > best[0]:
                best = (sil, km.labels_)
        if best[1] is not None:
            labels = best[1]
    regions = []
    for lab in np.unique(labels):
        el = np.sort(heavy[labels == lab])
        regions.append(region_entry(mesh, el, shares))
    regions.sort(key=lambda r: -r["share"])
    return regions


def region_entry(mesh, elements, shares) -> dict:
    C = np.asarray(mesh.vertices)[np.asarray(mesh.tets)[elements]].mean(axis=1)
    W = np.asarray(mesh.rest_volumes)[elements]
    return {
        "elements": [int(e) for e in elements],
        "share": float(np.clip(shares[elements].sum(), 0, 1)),
        "centroid": [float(c) for c in (C * W[:, None]).sum(0) / W.sum()],
    }
