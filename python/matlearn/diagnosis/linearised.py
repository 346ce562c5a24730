"""Stiffness sensitivities of the train residual by forward mode (tangents), not by re-simulation.

A spatial stiffness change (log E per element: the heterogeneity patches, a region boundary
move, a uniform scale, the clamp layer) enters the marker residual through the initial held pose
(a static equilibrium with the marker-nearest vertices prescribed) and through every step of the
linearised backward-Euler replay. `stiffness_jacobian` differentiates both:

* the held pose: K_ff dx_f = f_theta,f - K_fp dx_p with the clamped vertices fixed and the
  marker-nearest ones moved by the held pose's misfit-refinement passes (differentiated too,
  each equilibrium at its own pose: the poses are recomputed, a few static solves);
* the replay: `_core.time.LinearisedReplay.tangent`, k directions per pass sharing one
  factorisation per step (C++), the derivative of the markers' embedding points returned.

The result approximates the finite-difference Jacobian of `fitting.marker_residual` (tested
against it in tests/python/test_diagnosis_linearised.py); it is used where many directions are
needed (patches, boundary groups) and every decision made from it is re-checked by simulation.
Recordings with drive points are replayed with the driven vertices prescribed (their motion is
given: zero derivative).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

from .. import replay


def _held_pose_tangent(problem, model, rec, directions, refine: int = 3) -> np.ndarray:
    """(3n, k) derivative of the held initial pose (replay.initial_state, velocity zero) for
    log-stiffness directions (#T, k): the static equilibrium of the free vertices,
    K_ff dx_f = f_theta,f - K_fp dx_p, followed by the `refine` marker-misfit passes that move
    the prescribed (marker-nearest) vertices by the markers' remaining misfit; each equilibrium
    is differentiated at its own pose (the passes move the pose by up to a few % of the size)."""
    scene = problem.scene
    n = scene.mesh.num_vertices
    k = directions.shape[1]
    if rec.at_rest_initially:
        return np.zeros((3 * n, k))
    emb = problem.embedding(rec)
    seen = rec.seen[0]
    near = emb.nearest_vertices()[seen]
    uniq, inv = np.unique(near, return_inverse=True)
    is_fixed = np.zeros(n, bool)
    is_fixed[np.asarray(scene.fixed, int)] = True
    is_fixed[replay.drive_vertices(scene, rec)[0]] = True  # driven: at their targets, whatever the model
    held = is_fixed.copy()
    held[uniq] = True
    free = np.repeat(~held, 3)
    if not free.any():
        return np.zeros((3 * n, k))
    movable = ~is_fixed[uniq]
    passes = refine if movable.any() else 0
    zero = np.zeros((n, 3))
    dx = np.zeros((3 * n, k))

    def equilibrium(x):
        K = model.stiffness(x, zero, project_psd=False).tocsr()
        Ph = np.asarray(model.principal_kinematics(x, zero)[2], float)  # (#T, 3) principal stress
        F = np.asarray(model.force_map(x) @ (Ph[:, :, None] * directions[:, None, :]).reshape(-1, k))
        Kf = K[free]
        dx[free] = spla.splu(Kf[:, free].tocsc()).solve(np.ascontiguousarray(F[free] - Kf[:, ~free] @ dx[~free]))

    equilibrium(replay.initial_state(scene, model, rec, emb, refine=0)[0])
    if not passes:
        return dx
    Em = emb.matrix(n)[seen]
    wmax = emb.bary.max(axis=1)[seen]
    count = np.bincount(inv, minlength=len(uniq)).astype(float)
    for p in range(1, passes + 1):
        dmis = -(Em @ dx.reshape(n, 3 * k)).reshape(-1, 3, k) / wmax[:, None, None]
        dcorr = np.zeros((len(uniq), 3, k))
        np.add.at(dcorr, inv, dmis)
        dcorr /= count[:, None, None]
        dxv = dx.reshape(n, 3, k)
        dxv[uniq[movable]] += dcorr[movable]
        equilibrium(replay.initial_state(scene, model, rec, emb, refine=p)[0])
    return dx


def recording_tangent(problem, model, rec, directions):
    """(predicted markers (T, K, 3), their derivative (T, K, 3, k)) of one recording for
    log-stiffness directions (#T, k), through the scene's LinearisedReplay (its drive points
    prescribed)."""
    directions = np.ascontiguousarray(directions, float)
    return problem.remembered(rec, ("tangent", problem.fingerprint(model), directions),
                              lambda: _recording_tangent(problem, model, rec, directions))


def _recording_tangent(problem, model, rec, directions):
    from .fitting import rest_offset

    scene = problem.scene
    n = scene.mesh.num_vertices
    emb = problem.embedding(rec)
    x0, v0 = replay.initial_state(scene, model, rec, emb)
    dx0 = _held_pose_tangent(problem, model, rec, directions)
    runner, sim_t, x0, targets = problem.linearised_setup(model, rec, x0)
    X, dQ = runner.tangent(model, x0, v0, len(sim_t) - 1, np.zeros((n, 3)), dx0,
                           np.ascontiguousarray(directions, float),
                           np.asarray(emb.vertices, np.int64), np.asarray(emb.bary, float), targets=targets)
    problem.count()
    Q = np.einsum("kj,tkjd->tkd", emb.bary, X[:, emb.vertices])
    P = replay.interpolate_frames(sim_t, Q, rec.times) + rest_offset(problem, rec)[None]
    dP = replay.interpolate_frames(sim_t, dQ, rec.times)
    return P, dP


def patch_directions(labels) -> np.ndarray:
    """(#T, k) log-stiffness directions of patches: column p is 1 on the tets labelled p."""
    labels = np.asarray(labels, np.int64)
    return (labels[:, None] == np.arange(int(labels.max()) + 1)[None]).astype(float)


def stiffness_jacobian(problem, ctx, params: dict, directions, recs=None, fd_step: float = 0.1):
    """(r, J): the stacked train residual of the model `params` (fitting.marker_residual) and its
    Jacobian (N, k) for the log-stiffness directions (#T, k) (e.g. indicator columns of
    patches). Tangents where the recording is replayed linearised; finite differences of the
    model with E scaled by exp(fd_step * direction) otherwise."""
    from .effects import build_model
    from .fitting import marker_residual

    recs = problem.train if recs is None else recs
    directions = np.asarray(directions, float)
    if directions.ndim == 1:
        directions = directions[:, None]
    k = directions.shape[1]
    model = build_model(ctx, params)
    rs, Js = [], []
    for rec in recs:
        seen = rec.seen
        tangent_ok = (problem.fast_newton == 1 and problem.reuse_factor and model.correction is None
                      and not list(ctx.material.edits))
        if tangent_ok:
            try:
                P, dP = recording_tangent(problem, model, rec, directions)
                r = (P - rec.markers)[seen].ravel() / problem.object_size
                if np.all(np.isfinite(r)) and np.all(np.isfinite(dP)):
                    rs.append(r)
                    Js.append(dP[seen].reshape(-1, k) / problem.object_size)
                    continue
            except RuntimeError:
                pass
        r = marker_residual(problem, model, [rec])
        J = np.zeros((len(r), k))
        for j in range(k):
            J[:, j] = (marker_residual(problem, _scaled(ctx, params, fd_step * directions[:, j]), [rec])
                       - r) / fd_step
        rs.append(r)
        Js.append(J)
    return np.concatenate(rs), np.concatenate(Js, axis=0)


def scaled_context(ctx, log_scale):
    """A copy of ctx whose Young's modulus is times exp(log_scale[e]) per element."""
    from dataclasses import replace

    E = np.broadcast_to(np.asarray(ctx.material.youngs_modulus, float), (ctx.mesh.num_tets,))
    c2 = replace(ctx, material=replace(ctx.material, youngs_modulus=E * np.exp(log_scale)))
    c2.clamp_layer = ctx.clamp_layer
    return c2


def _scaled(ctx, params, log_scale):
    """The model of `params` with every element's Young's modulus times exp(log_scale[e])."""
    from .effects import build_model

    return build_model(scaled_context(ctx, log_scale), params)
