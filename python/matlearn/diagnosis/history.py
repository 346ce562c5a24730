"""History dependence: is the remaining residual a function of the state (Fh, Fhdot) at all?

Test. Take the best stateless explanation found (or the nominal model) with its uniform
stiffness refit (the stateless reference). Then let the material change with the body's
*history*, which a function of (Fh, Fhdot) cannot do:
* across recordings: every train recording after the first gets its own stiffness scale (the
  same body, the same states, but a material that was loaded before: Mullins damage,
  plastic set, ageing);
* in time: the second half of every recording gets its own stiffness scale and
  stiffness-damping shift (softening or yielding during the motion, loops that differ in
  loading and unloading).
History dependence is detected when this history model
1. cuts (rss + floor) of the stateless reference by the factor a further effect must reach,
2. is preferred by the score (it pays for its parameters), and
3. gains more than any stateless family of the library could still add to the reference
   (linearised gain of each family's sensitivities on the reference residual): a stateless
   effect the verdict missed, e.g. an amplitude-dependent stiffness seen as a different
   stiffness in a larger recording, must not pass for history.
Reported as outside the library: a correction N(Fh, Fhdot) cannot learn it.

Limitations: a pure change of rest shape (plastic set without stiffness change) shows up only
through the stiffness proxy; two halves is the coarsest split in time.
"""
from __future__ import annotations

import numpy as np

from .. import replay
from .effects import build_model
from .fitting import debias, linear_fit, rest_offset
from .problem import stack_residuals


def _params_for(params, shift, late):
    """(early, late) parameter dicts: stiffness shifted by `shift`, the late half further by
    late[0] in log stiffness and late[1] in the stiffness-damping parameter."""
    p1 = dict(params)
    s0 = float(np.asarray(p1.get("stiffness_scale", [0.0]), float)[0])
    p1["stiffness_scale"] = [s0 + shift]
    p2 = dict(p1)
    p2["stiffness_scale"] = [s0 + shift + late[0]]
    r0 = np.asarray(p2.get("rayleigh_damping", [0.0, 0.0]), float)
    p2["rayleigh_damping"] = [r0[0], r0[1] + late[1]]
    return p1, p2


def _rec_residual(problem, ctx, params, shift, late, rec):
    p1, p2 = _params_for(params, shift, late)

    def predict(rec):
        m1 = build_model(ctx, p1)
        m2 = m1 if late[0] == 0 and late[1] == 0 else build_model(ctx, p2)
        return _simulate_split(problem, m1, m2, rec) + rest_offset(problem, rec)[None]

    # the discretisation discrepancy removed per recording (as fitting.marker_residual does)
    return debias(problem, stack_residuals([rec], predict, problem.object_size), [rec])


def _residual(problem, ctx, params, x, recs, only=None, base=None):
    """Stacked residual of the history model x = [shared stiffness, per-recording shifts of
    recordings 1.., late stiffness, late damping]; `only` (recording indices) re-simulates
    those recordings and copies the others from `base` (a list of per-recording residuals)."""
    K = len(recs)
    out = []
    for k, rec in enumerate(recs):
        if only is not None and k not in only:
            out.append(base[k])
            continue
        shift = x[0] + (x[k] if k > 0 else 0.0)
        out.append(_rec_residual(problem, ctx, params, shift, x[K:K + 2], rec))
    return out


def _simulate_split(problem, m1, m2, rec):
    if m2 is m1:
        return problem.predict(m1, rec)
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


def _gauss_newton(problem, ctx, params, recs, x, free, iterations=2, step=0.07):
    """Gauss-Newton (Levenberg-damped, step-limited) over the entries `free` of x.
    Returns (x, per-recording residuals, rss)."""
    K = len(recs)
    parts = _residual(problem, ctx, params, x, recs)
    cost = float(sum(p @ p for p in parts))
    for _ in range(iterations):
        r = np.concatenate(parts)
        J = np.zeros((len(r), len(free)))
        for j, i in enumerate(free):
            xp = x.copy()
            xp[i] += step
            # a per-recording shift changes only its own recording
            only = [i] if 0 < i < K else None
            J[:, j] = (np.concatenate(_residual(problem, ctx, params, xp, recs, only, parts)) - r) / step
        JTJ = J.T @ J
        dx = -np.linalg.solve(JTJ + 1e-3 * np.diag(np.diag(JTJ) + 1e-300), J.T @ r)
        dx = np.clip(dx, -2, 2)
        xn = x.copy()
        xn[free] += dx
        pn = _residual(problem, ctx, params, xn, recs)
        cn = float(sum(p @ p for p in pn))
        if cn < cost:
            x, parts, cost = xn, pn, cn
        else:
            break
    return x, parts, cost


def check(problem, ctx, selected, rss_floor, say=None, add_factor=0.6, stateless=None):
    """{"detected", "explained", "score", "parameters"}; see the module docstring.
    stateless: {family: (N, k) sensitivities of the train residual} of the library's families
    (criterion 3; skipped when None)."""
    from .fitting import score

    params = dict(selected.params) if selected is not None else {}
    recs = problem.train
    K = len(recs)
    x = np.zeros(K + 2)
    x_ref, parts_ref, ref = _gauss_newton(problem, ctx, params, recs, x, [0])
    nothing = {"detected": False, "explained": 0.0, "score": 0.0, "parameters": {}}
    if ref <= rss_floor:  # nothing left beyond noise and discretisation
        return nothing
    free = list(range(K + 2))
    x_h, _, cost = _gauss_newton(problem, ctx, params, recs, x_ref.copy(), free)
    n = float(sum(len(rec.times) for rec in recs))
    dof = sum(len(v) for v in params.values()) + 1
    s_ref = score(ref, dof, n, rss_floor)
    s_hist = score(cost, dof + K + 1, n, rss_floor)
    gain = ref - cost
    r_ref = np.concatenate(parts_ref)
    best_stateless, best_name = 0.0, None
    for name, Jn in (stateless or {}).items():
        if name in params:
            continue
        _, rss = linear_fit(np.asarray(Jn, float), r_ref)
        if ref - rss > best_stateless:
            best_stateless, best_name = ref - rss, name
    detected = (cost + rss_floor < add_factor * (ref + rss_floor)) and s_hist < s_ref \
        and gain > best_stateless
    if say:
        say(f"history check: stateless rss {ref:.3e} -> {cost:.3e} with history parameters {np.round(x_h, 3)}"
            f" (best stateless addition {best_name} {best_stateless:.3e}), detected {detected}")
    return {
        "detected": bool(detected),
        "explained": float(np.clip(gain / max(ref, 1e-300), 0, 1)),
        "score": s_hist,
        "parameters": {"recording_stiffness_scales": [float(np.exp(v)) for v in x_h[1:K]],
                       "late_stiffness_scale": float(np.exp(x_h[K])),
                       "late_alpha_stiffness_shift": float(x_h[K + 1] * 0.1 / ctx.omega)},
    }
