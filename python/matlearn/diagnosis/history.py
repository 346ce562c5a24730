"""History dependence: is the remaining residual a function of the state (Fh, Fhdot) at all?

Test. Take the best stateless explanation found (or the nominal model) with its uniform
stiffness refit (the stateless reference). Then let the material change with the body's
*history*, which a function of (Fh, Fhdot) cannot do:
* across recordings: every train recording after the first gets its own stiffness scale (the
  same body, the same states, but a material that was loaded before: Mullins damage,
  plastic set, ageing);
* in time: the second half of every recording gets its own stiffness scale and
  stiffness-damping shift (softening or yielding during the motion, loops that differ in
  loading and unloading, a friction whose relative damping grows as the amplitude decays);
* in the equilibrium: every recording gets its own constant marker offset in the body's 3 main
  displacement patterns (a permanent set shifts the equilibrium a recording oscillates about),
  where the stateless models share one (their static error is the same in every recording).
  Used only when every recording spans OFFSET_PERIODS periods of the dominant oscillation.
* in the order strains were reached (the damage model, `_damage_fit`, when `DAMAGE` is on and
  the `where` step's strains are given): every element softened in proportion to the largest
  strain it has reached so far (a running maximum over the recordings in their order and over
  time, piecewise constant over DAMAGE_SEGMENTS segments per recording), one parameter. A virgin
  body's first loading is stiffer than everything after it although it is the largest motion,
  the opposite of any amplitude-dependent stiffness. Its stateless twin is the same pattern fixed
  at what all the recordings reached (mesh error and heterogeneity concentrate where strain
  does). Detected (`decide_damage`) when it softens, explains at least half of the reference's
  residual above the floor, is preferred by the score, its twin gains at most half as much, and
  no stateless rival fits as well or scores better.
History dependence is detected (`decide`) when this history model
1. cuts (rss + floor) of the stateless reference by the factor a further effect must reach,
2. is preferred by the score (BIC: it pays for its K + 1 parameters), and
3. beats, in residual and in BIC, every stateless rival: the reference plus one library family
   (the two with the largest linearised gain, and Rayleigh damping whenever the late damping
   shift is used), refitted *by simulation* on the very residual
   the history model is judged on. The history model also absorbs stateless errors (a missed
   amplitude-dependent stiffness looks like a different stiffness in a larger recording, a
   missed damping like a late damping shift), so it must explain the data better than a
   function of the state does with fewer parameters. The rivals are simulated, not
   linearised: a linearisation about the nominal model can be far off either way for damping
   and nonlinearity families, and an oscillation's phase makes their fit multimodal, so they
   are fitted by continuation in time (the early part of each recording first) from two
   starts.
Reported as outside the library: a correction N(Fh, Fhdot) cannot learn it.

Limitations: a set formed before the first recording is indistinguishable from another rest
shape; two halves is the coarsest split in time; with two train
recordings of different amplitudes a body damaged by the larger one and a stateless softening
differ only within recordings (the damaged body stays soft as the motion decays), so a weak
history effect is not claimed.
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
    n = len(replay.simulation_times(problem.scene, rec))
    return _simulate_segments(problem, [m1, m2], [0, n // 2, n - 1], rec)


def _simulate_segments(problem, models, bounds, rec):
    """Markers at rec.times of one recording simulated with models[i] over the simulation steps
    bounds[i] .. bounds[i + 1] (the state carried across), from the first model's start state
    (Problem.start_state, as every prediction starts; kept in the problem's store:
    Problem.remembered)."""
    parts = ("segments", problem.fast_newton, problem.estimate_velocity,
             tuple(problem.fingerprint(m) for m in models), tuple(int(b) for b in bounds))
    runs = sum(1 for a, b in zip(bounds[:-1], bounds[1:]) if b > a)
    return problem.remembered(rec, parts, lambda: (_segments(problem, models, bounds, rec),), runs)[0]


def _segments(problem, models, bounds, rec):
    """The simulation of _simulate_segments: with one Newton iteration per step through the
    problem's linearised replay (Problem.linearised_setup, as every fast prediction: drive
    points prescribed, the factor reused), else the scene's integrator."""
    scene = problem.scene
    emb = problem.embedding(rec)
    sim_t = replay.simulation_times(scene, rec)
    x, v = (np.asarray(a, float) for a in problem.start_state(models[0], rec))
    zero = np.zeros((scene.mesh.num_vertices, 3))
    linearised = problem.fast_newton == 1 and problem.reuse_factor
    if linearised:
        runner, _, x, targets = problem.linearised_setup(models[0], rec, x)
    else:
        didx, dtar = replay.drive_vertices(scene, rec)
    Xs = []
    for model, a, b in zip(models, bounds[:-1], bounds[1:]):
        if b <= a:
            continue
        if linearised:
            X, V = runner.simulate(model, x, v, b - a, zero,
                                   targets=None if targets is None else np.ascontiguousarray(targets[a:b]))
        else:
            integ = scene.integrator(model, max_newton=problem.fast_newton)
            if len(didx):
                integ.set_prescribed(didx)
                integ.set_state(x, v)
                X, V = integ.simulate_constrained(replay.interpolate_frames(rec.times, dtar, sim_t[a + 1: b + 1]),
                                                  zero)
            else:
                integ.set_state(x, v)
                X, V = integ.simulate(b - a, zero, 1)
        problem.count()
        Xs.append(X if a == 0 else X[1:])
        x, v = np.asarray(X[-1]), np.asarray(V[-1])
    X = np.concatenate(Xs)
    return replay.interpolate_frames(sim_t, emb.apply(X), rec.times)


OFFSET_PERIODS = 1.5  # a constant offset absorbs <= 2 / (pi n)^2 = 9 % of an oscillation over n = 1.5 periods


def _offset_basis(recs, modes=3):
    """Per recording, the (n_k, modes) marker-space columns of a constant displacement in each
    of the body's `modes` main displacement patterns (right singular vectors of the observed
    marker displacements of all recordings), in the residual's layout. A permanent set shifts
    the equilibrium a recording oscillates about, inside the span of how the body moves.
    None when the recordings do not share one marker set."""
    try:
        M = {int(np.asarray(r.marker_rest).shape[0]) for r in recs}
        if len(M) != 1:
            return None
        D = np.concatenate([np.nan_to_num(np.asarray(r.markers, float) - np.asarray(r.marker_rest, float)[None])
                            .reshape(len(r.times), -1) for r in recs])
    except (AttributeError, ValueError):
        return None
    if not np.any(D):
        return None
    V = np.linalg.svd(D, full_matrices=False)[2][:modes]
    out = []
    for r in recs:
        seen = np.asarray(r.seen, bool)
        cols = [np.broadcast_to(v.reshape(-1, 3), (len(r.times),) + (seen.shape[1], 3))[seen].ravel()
                for v in V]
        out.append(np.stack(cols, axis=1))
    return out


def _projector(basis, per_recording):
    """parts -> parts with constant marker offsets in `basis` profiled out (least squares): one
    set of coefficients per recording (the history model) or one shared by all (the stateless
    reference: a static error of a stateless model, e.g. a wrong sag, is the same in every
    recording). Identity when basis is None."""
    if basis is None:
        return lambda parts: parts
    if per_recording:
        def proj(parts):
            return [q - B @ np.linalg.lstsq(B, q, rcond=None)[0] for q, B in zip(parts, basis)]
        return proj
    B = np.concatenate(basis)
    sizes = np.cumsum([len(b) for b in basis])[:-1]

    def proj(parts):
        r = np.concatenate(parts)
        return np.split(r - B @ np.linalg.lstsq(B, r, rcond=None)[0], sizes)
    return proj


def _lm(fun, x, free, K, parallel, iterations=2, step=0.07, stop=-1.0):
    """Gauss-Newton (Levenberg-damped, step-limited) over the entries `free` of x for
    fun(x, only, base) -> per-recording residuals (entries 1..K-1 of x touch only their own
    recording); stops early once the rss is <= `stop`. `parallel` (Problem.parallel) runs the
    Jacobian's columns. Returns (x, per-recording residuals, rss)."""
    parts = fun(x, None, None)
    cost = float(sum(p @ p for p in parts))
    for _ in range(iterations):
        if cost <= stop:
            break
        r = np.concatenate(parts)
        J = np.zeros((len(r), len(free)))

        def column(i, parts=parts):
            xp = x.copy()
            xp[i] += step
            return np.concatenate(fun(xp, [i] if 0 < i < K else None, parts))

        for j, col in enumerate(parallel([lambda i=i: column(i) for i in free])):
            J[:, j] = (col - r) / step
        JTJ, g = J.T @ J, J.T @ r
        improved = False
        for mu in (1e-3, 1e-1, 1e1):  # Levenberg damping raised when a step fails
            dx = -np.linalg.solve(JTJ + mu * np.diag(np.diag(JTJ) + 1e-300), g)
            dx = np.clip(dx, -2, 2)
            xn = x.copy()
            xn[free] += dx
            pn = fun(xn, None, None)
            cn = float(sum(p @ p for p in pn))
            if cn < cost:
                x, parts, cost, improved = xn, pn, cn, True
                break
        if not improved:
            break
    return x, parts, cost


def _gauss_newton(problem, ctx, params, recs, x, free, iterations=2, step=0.07, proj=None):
    """The history model x = [shared stiffness, per-recording shifts, late stiffness, late
    damping] fitted over the entries `free` (_lm), `proj` (per-recording, or None) profiling
    out marker offsets. Returns (x, per-recording residuals, rss)."""
    proj = proj or (lambda parts: parts)

    def fun(x, only, base):
        return proj(_residual(problem, ctx, params, x, recs, only, base))

    return _lm(fun, x, free, len(recs), problem.parallel, iterations, step)


def _stateless(problem, ctx, params, x_ref, recs, name, theta0, iterations=3, stop=-1.0, proj=None):
    """A library family added to the stateless reference, refitted by simulation together with
    the shared stiffness, on exactly the residual the history model is judged on. An
    oscillation's accumulated phase makes the fit multimodal, and a linearisation about the
    nominal model can land in a side valley. So it is fitted by continuation in time (first on
    the early part of every recording, where phases have not yet drifted apart, then on the
    whole), from the reference (family at zero) and from the linearised estimate theta0, the
    best kept; it stops early once its rss is <= `stop` (it already beats the history model).
    Returns rss."""
    K = len(recs)
    k = len(theta0)
    proj = proj or (lambda parts: parts)

    def fun_of(share):
        def fun(x, only, base):
            p = dict(params)
            p[name] = list(x[K + 2:])
            y = np.zeros(K + 2)
            y[0] = x[0]
            parts = proj(_residual(problem, ctx, p, y, recs))
            return parts if share >= 1 else [q[: max(1, int(share * len(q)))] for q in parts]
        return fun

    free = [0] + list(range(K + 2, K + 2 + k))
    best = np.inf
    starts = [np.zeros(k)]
    th = np.clip(np.nan_to_num(np.asarray(theta0, float)), -2, 2)
    if np.abs(th).max(initial=0.0) > 1e-6:
        starts.append(th)
    for t0 in starts:
        x = np.concatenate([np.zeros(K + 2), t0])
        x[0] = x_ref[0]
        x = _lm(fun_of(0.4), x, free, K, problem.parallel, iterations)[0]
        best = min(best, _lm(fun_of(1.0), x, free, K, problem.parallel, iterations, stop=stop)[2])
        if best <= stop:
            break
    return best


DAMAGE = True  # the damage model in `check` (off: the first path alone, as until session 9)
DAMAGE_SEGMENTS = 6  # piecewise-constant damage over this many equal time segments per recording


def damage_strains(fields) -> list:
    """Per train recording (sampled times, (F, m) largest principal strain magnitude |s - 1| of
    every element): the strain of the nominal model following the markers (the `where` step's
    residual fields, one per train recording, in order)."""
    return [(np.asarray(f.times, float), np.abs(np.asarray(f.Fh, float) - 1.0).max(axis=2)) for f in fields]


def _damage_schedule(problem, recs, strains, segments=DAMAGE_SEGMENTS):
    """Per recording (simulation-step bounds of `segments` equal segments, [D per segment]): D
    the largest strain each element has reached so far, over the recordings in their order and
    over time (a running maximum of `strains`), taken at each segment's start (a virgin body's
    first loading is undamaged); and the final D (what all the recordings reached)."""
    out, prev = [], None
    for rec, (ft, s) in zip(recs, strains):
        run = np.maximum.accumulate(np.asarray(s, float), axis=0)
        if prev is not None:
            run = np.maximum(run, prev[None])
        sim_t = replay.simulation_times(problem.scene, rec)
        bounds = np.linspace(0, len(sim_t) - 1, segments + 1).astype(int)
        Ds = []
        for a in bounds[:-1]:
            i = int(np.searchsorted(ft, sim_t[a], side="right")) - 1
            Ds.append(run[i] if i >= 0 else (prev if prev is not None else np.zeros(run.shape[1])))
        prev = run[-1]
        out.append((bounds, Ds))
    return out, prev


def _damage_residual(problem, ctx, params, shift, c, bounds, Ds, rec):
    """Residual of one recording simulated with every element's log stiffness lowered by
    c D_e / d_ref in each segment (D per segment), the uniform stiffness shifted by `shift`."""
    from dataclasses import replace

    from ..materials import Material

    mat = ctx.material
    E = np.broadcast_to(np.asarray(mat.youngs_modulus, float), (ctx.mesh.num_tets,))
    p = dict(params)
    p["stiffness_scale"] = [float(np.asarray(params.get("stiffness_scale", [0.0]), float)[0]) + shift]
    models = []
    for D in Ds:
        e = E * np.exp(np.clip(c * np.asarray(D) / ctx.d_ref, -3, 3))
        models.append(build_model(replace(ctx, material=Material(mat.model, e, mat.poisson_ratio, mat.density,
                                                                   list(mat.edits))), p))

    def predict(rec):
        return _simulate_segments(problem, models, bounds, rec) + rest_offset(problem, rec)[None]

    return debias(problem, stack_residuals([rec], predict, problem.object_size), [rec])


def _damage_fit(problem, ctx, params, recs, strains, s0, proj, iterations=4):
    """A damage model: every element softened in proportion to the largest strain it has seen so
    far (running maximum over the recordings in their order and over time), one parameter c
    (log stiffness per d_ref of strain) with the shared stiffness; and its stateless twin: the
    same pattern fixed at what all recordings reached (a stiffness field a function of the state
    can have: mesh error and heterogeneity concentrate where strain does). Returns ((rss, c),
    (twin rss, twin c))."""
    sched, final = _damage_schedule(problem, recs, strains)
    out = []
    for stateless in (False, True):
        def fun(x, only, base, stateless=stateless):
            parts = []
            for rec, (bounds, Ds) in zip(recs, sched):
                Ds = [final] * len(Ds) if stateless else Ds
                parts.append(_damage_residual(problem, ctx, params, x[0], x[1], bounds, Ds, rec))
            return proj(parts)
        x, _, cost = _lm(fun, np.array([s0, 0.0]), [0, 1], 1, problem.parallel, iterations)
        out.append((cost, float(x[1])))
    return out[0], out[1]


def decide_damage(ref, dmg, twin, c, n, dof, rss_floor, explained=0.5):
    """The damage model's own criteria: it softens (c < 0: damage, Mullins softening; a stateless
    amplitude dependence acts in the opposite order in time, the largest, first swing most
    affected), explains at least `explained` of the reference's residual above the floor, is
    preferred by the score over the reference, and at least half of its gain comes from the
    order in which the strains were reached (its stateless twin, the same pattern fixed,
    gains at most half as much)."""
    from .fitting import score

    return bool(c < 0 and ref - dmg >= explained * (ref - rss_floor)
                and score(dmg, dof + 1, n, rss_floor) < score(ref, dof, n, rss_floor)
                and twin - dmg >= 0.5 * (ref - dmg))


def decide(ref, cost, alternatives, n, dof, K, rss_floor, add_factor=0.6, extra=None):
    """The decision on fitted residuals: `ref` the stateless reference's rss (dof parameters),
    `cost` the history model's (dof + extra, default K + 1), `alternatives` {family: (rss,
    parameters)} of the
    reference plus one library family each (the stateless rivals). History dependence needs
    1. a cut of (rss + floor) to add_factor (what any further effect must reach),
    2. a lower BIC than the reference, and
    3. a lower residual and BIC than every stateless rival: a missed function of (Fh, Fhdot)
       that explains the per-recording / late change at least as well is not history.
    Returns (detected, name of the best rival or None)."""
    from .fitting import score

    s_hist = score(cost, dof + (K + 1 if extra is None else extra), n, rss_floor)
    ok = cost + rss_floor < add_factor * (ref + rss_floor) and s_hist < score(ref, dof, n, rss_floor)
    best = None
    for name, (rss, k) in alternatives.items():
        if best is None or rss < alternatives[best][0]:
            best = name
        if rss <= cost or score(rss, dof + k, n, rss_floor) <= s_hist:
            ok = False
    return bool(ok), best


def check(problem, ctx, selected, rss_floor, say=None, add_factor=0.6, stateless=None, rivals=2, strains=None):
    """{"detected", "explained", "score", "parameters", "reference"}; see the module docstring.
    reference: the stateless reference's parameters (the best the library's stateless families
    do, with the uniform stiffness refit).
    stateless: {family: (N, k) sensitivities of the train residual} of the library's families
    (criterion 3: those whose linearised gain on the reference residual reaches the history
    model's gain are candidates; the `rivals` best of them are refitted by simulation; skipped
    when None).
    strains: `damage_strains` of the train recordings, for the damage model (skipped when None)."""
    from .fitting import score

    params = dict(selected.params) if selected is not None else {}
    recs = problem.train
    K = len(recs)
    x = np.zeros(K + 2)
    # constant marker offsets in the body's main displacement patterns: shared by all recordings
    # in every stateless model, one set per recording in the history model (a permanent set)
    # (only where every recording spans OFFSET_PERIODS periods of the dominant oscillation: over a
    # shorter window an oscillation's mean is not small, and offsets would absorb it)
    periods = min(float(r.times[-1] - r.times[0]) for r in recs) * ctx.omega / (2 * np.pi)
    basis = _offset_basis(recs) if periods >= OFFSET_PERIODS else None
    shared, per = _projector(basis, False), _projector(basis, True)
    n_modes = 0 if basis is None else basis[0].shape[1]
    # (the stiffness first without the offsets: profiling them out changes the landscape, and a
    # reference stuck in a side valley would hand the history model a false gain)
    x, _, _ = _gauss_newton(problem, ctx, params, recs, x, [0])
    x_ref, parts_ref, ref = _gauss_newton(problem, ctx, params, recs, x, [0], proj=shared)
    nothing = {"detected": False, "explained": 0.0, "score": 0.0, "parameters": {}, "reference": params}
    if ref <= rss_floor:  # nothing left beyond noise and discretisation
        return nothing
    free = list(range(K + 2))
    x_h, _, cost = _gauss_newton(problem, ctx, params, recs, x_ref.copy(), free, proj=per)
    n = float(sum(len(rec.times) for rec in recs))
    dof = sum(len(v) for v in params.values()) + 1 + n_modes
    extra = K + 1 + n_modes * (K - 1)
    gain = ref - cost
    r_ref = np.concatenate(parts_ref)
    lin = {}
    for name, Jn in (stateless or {}).items():
        if name in params or name == "stiffness_scale":
            continue
        th, rss = linear_fit(np.asarray(Jn, float), r_ref)
        lin[name] = (th, rss)
    # stateless rivals: the `rivals` families with the largest linearised gain on the reference
    # residual, refitted by simulation (a linearisation about the nominal model can be far off
    # either way for damping or nonlinearity families); only needed when the history model
    # passes the other criteria
    passes = decide(ref, cost, {}, n, dof, K, rss_floor, add_factor, extra)[0]
    # the damage model (a softening that follows the largest strain reached so far), against its
    # own stateless twin; it needs the same stateless rivals
    dmg = c_dmg = twin = None
    damaged = False
    if DAMAGE and strains is not None and len(strains) == K:
        (dmg, c_dmg), (twin, _) = _damage_fit(problem, ctx, params, recs, strains, x_ref[0], shared)
        damaged = decide_damage(ref, dmg, twin, c_dmg, n, dof, rss_floor)
    cands = sorted(lin, key=lambda nm: lin[nm][1])[:rivals] if passes or damaged else []
    # a missed viscous damping grows the residual with time, which the late-half damping shift
    # mimics: the library's damping family is always a rival when that shift is used
    if passes and "rayleigh_damping" in lin and "rayleigh_damping" not in cands and abs(x_h[K + 1]) > 0.1:
        cands.append("rayleigh_damping")
    alternatives = {}
    stop = min(cost if passes else np.inf, dmg if damaged else np.inf)  # a rival's fit may stop below it
    for name in cands:
        k = len(lin[name][0]) + (1 if name == "heterogeneity" else 0)
        alternatives[name] = (_stateless(problem, ctx, params, x_ref, recs, name, lin[name][0], stop=stop,
                                         proj=shared), k)
    detected, best_name = decide(ref, cost, alternatives, n, dof, K, rss_floor, add_factor, extra)
    s_hist = score(cost, dof + extra, n, rss_floor)
    if damaged:  # a stateless rival that fits as well or scores better is a function of the state
        s_dmg = score(dmg, dof + 1, n, rss_floor)
        damaged = all(rss > dmg and score(rss, dof + k, n, rss_floor) > s_dmg
                      for rss, k in alternatives.values())
        if damaged and (not detected or s_dmg < s_hist):
            detected, gain, s_hist = True, ref - dmg, s_dmg
    if say:
        alt = ", ".join(f"{nm} {v[0]:.3e} (linearised {lin[nm][1]:.3e})" for nm, v in alternatives.items())
        dm = "" if dmg is None else (f"; damage model rss {dmg:.3e} (log stiffness {c_dmg:.3f} per d_ref of the"
                                     f" largest strain reached), its stateless twin {twin:.3e}")
        say(f"history check: stateless rss {ref:.3e} -> {cost:.3e} with history parameters {np.round(x_h, 3)}{dm};"
            f" stateless rivals by simulation: {alt or 'not needed'}; detected {detected}")
    reference = dict(params)
    reference["stiffness_scale"] = [float(np.asarray(params.get("stiffness_scale", [0.0]), float)[0] + x_ref[0])]
    parameters = {"recording_stiffness_scales": [float(np.exp(v)) for v in x_h[1:K]],
                  "late_stiffness_scale": float(np.exp(x_h[K])),
                  "late_alpha_stiffness_shift": float(x_h[K + 1] * 0.1 / ctx.omega)}
    if c_dmg is not None:
        parameters["damage_log_stiffness_per_strain"] = float(c_dmg / ctx.d_ref)
    return {
        "detected": bool(detected),
        "reference": reference,
        "explained": float(np.clip(gain / max(ref, 1e-300), 0, 1)),
        "score": s_hist,
        "parameters": parameters,
    }
