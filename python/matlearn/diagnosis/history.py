"""History dependence: is the remaining residual a function of the state (Fh, Fhdot) at all?

Test. Take the best stateless explanation found (or the nominal model). Let the material
change *in time*: the second half of every train recording gets its own stiffness scale and
stiffness-damping shift (2 parameters) while the first half keeps the stateless model. A
function of (Fh, Fhdot) visits the same states in both halves and gains nothing from this; a
material that softens with loading (Mullins damage), yields (plasticity) or whose loops differ in
loading and unloading does. Detected when the time split cuts (rss + floor) by the same factor a
further effect must reach, and the split model is preferred by the score. Reported as outside
the library: a correction N(Fh, Fhdot) cannot learn it.

Limitations: a pure change of rest shape (plastic set without stiffness change) shows up only
through the stiffness proxy; two halves is the coarsest split.
"""
from __future__ import annotations

import numpy as np

from .. import replay
from .effects import build_model
from .fitting import rest_offset


def _split_residual(problem, ctx, params, theta, recs):
    out = []
    for rec in recs:
        m1 = build_model(ctx, params)
        p2 = dict(params)
        s0 = np.asarray(p2.get("stiffness_scale", [0.0]), float)
        p2["stiffness_scale"] = [s0[0] + theta[0]]
        r0 = np.asarray(p2.get("rayleigh_damping", [0.0, 0.0]), float)
        p2["rayleigh_damping"] = [r0[0], r0[1] + theta[1]]
        m2 = build_model(ctx, p2)
        seen = rec.seen
        try:
            P = _simulate_split(problem, m1, m2, rec) + rest_offset(problem, rec)[None]
            r = (P - rec.markers)[seen].ravel() / problem.object_size
            if not np.all(np.isfinite(r)):
                raise RuntimeError
        except RuntimeError:
            r = np.full(3 * int(seen.sum()), 1.0)
        out.append(r)
    return np.concatenate(out)


def _simulate_split(problem, m1, m2, rec):
    scene = problem.scene
    emb = problem.embedding(rec)
    sim_t = replay.simulation_times(scene, rec)
    half = len(sim_t) // 2
    x0, v0 = replay.initial_state(scene, m1, rec, emb)
    didx, dtar = replay.drive_vertices(scene, rec)
    Xs, Vs = [], []
    state = (np.asarray(x0), np.asarray(v0))
    for model, a, b in ((m1, 0, half), (m2, half, len(sim_t) - 1)):
        integ = scene.integrator(model, max_newton=problem.fast_newton)
        zero = np.zeros((scene.mesh.num_vertices, 3))
        if len(didx):
            integ.set_prescribed(didx)
            integ.set_state(*state)
            targets = replay.interpolate_frames(rec.times, dtar, sim_t[a + 1: b + 1])
            X, V = integ.simulate_constrained(targets, zero)
        else:
            integ.set_state(*state)
            X, V = integ.simulate(b - a, zero, 1)
        problem.simulations += 1
        Xs.append(X if a == 0 else X[1:])
        Vs.append(V if a == 0 else V[1:])
        state = (np.asarray(X[-1]), np.asarray(V[-1]))
    X = np.concatenate(Xs)
    return replay.interpolate_frames(sim_t, emb.apply(X), rec.times)


def check(problem, ctx, selected, rss_floor, say=None, add_factor=0.6):
    """{"detected", "explained", "score", "parameters"}; see the module docstring."""
    from .fitting import score

    params = dict(selected.params) if selected is not None else {}
    recs = problem.train
    r_base = _split_residual(problem, ctx, params, [0.0, 0.0], recs)
    base = float(r_base @ r_base)
    if base < 2.5 * rss_floor:
        return {"detected": False, "explained": 0.0, "score": 0.0, "parameters": {}}
    # Gauss-Newton in the two split parameters, two iterations
    th = np.zeros(2)
    r, cost = r_base, base
    step = 0.07
    for _ in range(2):
        J = np.stack([(_split_residual(problem, ctx, params, th + step * e, recs) - r) / step
                      for e in np.eye(2)], axis=1)
        JTJ = J.T @ J
        dx = -np.linalg.solve(JTJ + 1e-3 * np.diag(np.diag(JTJ) + 1e-300), J.T @ r)
        dx = np.clip(dx, -2, 2)
        rn = _split_residual(problem, ctx, params, th + dx, recs)
        if float(rn @ rn) < cost:
            th, r, cost = th + dx, rn, float(rn @ rn)
        else:
            break
    n = float(sum(len(rec.times) for rec in recs))
    dof = sum(len(v) for v in params.values())
    s_base = score(base, dof, n, rss_floor)
    s_split = score(cost, dof + 2, n, rss_floor)
    detected = (cost + rss_floor < add_factor * (base + rss_floor)) and s_split < s_base
    if say:
        say(f"history check: rss {base:.3e} -> {cost:.3e} with a time split {th}, detected {detected}")
    return {
        "detected": bool(detected),
        "explained": float(np.clip((base - cost) / max(base, 1e-300), 0, 1)),
        "score": s_split,
        "parameters": {"late_stiffness_scale": float(np.exp(th[0])),
                       "late_alpha_stiffness_shift": float(th[1] * 0.1 / ctx.omega)},
    }
