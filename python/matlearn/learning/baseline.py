"""Baseline: Wang et al. 2015-style parameter identification. Fit Young's modulus E, Poisson
ratio nu and the Rayleigh coefficients alpha_mass, alpha_stiffness of a standard law
(co-rotated or neo-Hookean) by nonlinear least squares on forward-simulated marker trajectories
of the train recordings (scipy.optimize.least_squares, finite-difference Jacobian whose columns
run on the cores (matlearn.parallel); E and the alphas in log space, nu bounded to [0, 0.49])."""
from __future__ import annotations

import inspect
import threading

import numpy as np
from scipy.optimize import least_squares

from ..embedding import embed_points
from ..materials import Damping, Material
from ..parallel import pmap
from ..replay import interpolate_frames, score, simulate_recording


FAILED_PCT = 100.0  # residual (% of size) per sample when a trial model cannot be simulated
# the finite-difference Jacobian's columns (independent simulations) on the cores: scipy >= 1.16
# maps them with `workers`; the columns, and so the fit, are bitwise the serial ones
_WORKERS = {"workers": pmap} if "workers" in inspect.signature(least_squares).parameters else {}


def marker_residual_pct(scene, model, recs, embs) -> np.ndarray:
    """The train markers' residual (model - observed, seen samples, % of the object size) of
    `model` replayed through recordings `recs` (embeddings `embs`); a recording the model cannot
    simulate gives FAILED_PCT per sample (a trial point of a fit, rejected by its step control)."""
    def one(pair):
        rec, emb = pair
        seen = rec.seen
        try:
            sim = simulate_recording(scene, model, rec)
            P = interpolate_frames(sim[0], emb.apply(sim[1]), rec.times)
            r = ((P - rec.markers)[seen] / scene.object_size * 100.0).ravel()
        except RuntimeError:
            r = np.full(3 * int(seen.sum()), FAILED_PCT)
        return r if np.all(np.isfinite(r)) else np.full(3 * int(seen.sum()), FAILED_PCT)

    return np.concatenate(pmap(one, list(zip(recs, embs))))  # the recordings on the cores


def _unpack(p, base: Material, law: str, alpha_mass: float | None = None):
    E, nu, aK = np.exp(p[0]), p[1], np.exp(p[3])
    aM = np.exp(p[2]) if alpha_mass is None else alpha_mass
    mat = Material(law, float(E), float(nu), base.density)
    return mat, Damping(float(aM), float(aK))


def fit_parameters(scene, law: str = "corotated", max_evaluations: int = 40, log=None,
                   alpha_mass: float | None = None, start: dict | None = None) -> dict:
    """Returns dict(material, damping, train_rms_pct, evaluations). alpha_mass: None (fitted)
    or a fixed value (1/s): the 3-parameter fit of E, nu, alpha_K that the learner's own model
    space contains (learning/start.py); start: a previous fit's result to start from."""
    recs = [r for r in scene.recordings_with_role("train") if r.num_markers > 0]
    if not recs:
        raise ValueError("baseline: the scene has no train recording with markers")
    embs = [embed_points(scene.mesh, r.marker_rest) for r in recs]
    m0, d0 = scene.material, scene.damping
    nu0 = float(np.mean(m0.poisson_ratio))
    p0 = np.array([np.log(float(np.mean(m0.youngs_modulus))), min(nu0, 0.48),
                   np.log(max(d0.alpha_mass, 1e-3)), np.log(max(d0.alpha_stiffness, 1e-4))])
    lo = np.array([p0[0] - 5, 0.0, np.log(1e-6), np.log(1e-7)])
    hi = np.array([p0[0] + 5, 0.49, np.log(1e3), np.log(1.0)])
    if start is not None:
        p0 = np.array([np.log(float(np.mean(start["material"].youngs_modulus))),
                       float(np.mean(start["material"].poisson_ratio)),
                       np.log(max(start["damping"].alpha_mass, 1e-6)),
                       np.log(max(start["damping"].alpha_stiffness, 1e-7))])
    free = np.array([True, True, alpha_mass is None, True])
    if alpha_mass is not None:  # exp(p[2]) is replaced by the fixed value in _unpack
        p0[2] = np.log(max(alpha_mass, 1e-300))
    count = [0]
    lock = threading.Lock()  # the finite-difference columns are evaluated in parallel (pmap)

    def full(q):
        p = p0.copy()
        p[free] = q
        return p

    def residual(q):
        with lock:
            count[0] += 1
            k = count[0]
        p = full(q)
        mat, damp = _unpack(p, m0, law, alpha_mass)
        r = marker_residual_pct(scene, scene.model(material=mat, damping=damp), recs, embs)
        if log:
            log(f"  baseline eval {k}: E={np.exp(p[0]):.4g} nu={p[1]:.3f} "
                f"aM={np.exp(p[2]):.3g} aK={np.exp(p[3]):.3g} rms={np.sqrt(np.mean(r**2)):.3f}%")
        return r

    sol = least_squares(residual, np.clip(p0, lo + 1e-9, hi - 1e-9)[free], bounds=(lo[free], hi[free]),
                        max_nfev=max_evaluations, diff_step=1e-3,
                        x_scale=np.array([1.0, 0.05, 1.0, 1.0])[free], **_WORKERS)
    mat, damp = _unpack(full(sol.x), m0, law, alpha_mass)
    return {"material": mat, "damping": damp, "evaluations": count[0],
            "train_rms_pct": float(np.sqrt(np.mean(sol.fun**2)))}


def baseline_test_errors(scene, fit: dict) -> list[float]:
    """Max error (% of size) per test recording of the fitted-parameter model."""
    model = scene.model(material=fit["material"], damping=fit["damping"])
    return [r["max_error_pct"] for r in score(scene, model, "test")["recordings"]]
