"""The damage model of the history test (diagnosis/history.py: a softening that follows the
largest strain each element has reached so far) on synthetic residuals: one mode per recording,
an analytic oscillation whose stiffness follows a per-time log stiffness, so the whole decision
runs in well under a second. A body damaged by its first loading (the same drop twice: the
first swing of the first is virgin, everything after is damaged) is detected, which the rule
without the damage model misses; a stateless softening (stiffness a function of the current
amplitude) is not taken for damage."""
from types import SimpleNamespace

import numpy as np

from matlearn.diagnosis import history

T = np.linspace(0.0, 0.3, 240)
OMEGA = 60.0
ZETA = 2.0
SIGMA = 2e-4
D_REF = 0.02


def _motion(kind, amp, logk):
    """Displacement (strain units) of one mode with per-sample log stiffness `logk`: a drop from
    rest about a sagged equilibrium (its first swing is the largest strain), or a release from a
    held pose (largest at t = 0)."""
    dt = np.diff(T, prepend=0.0)
    phase = np.cumsum(OMEGA * np.exp(0.5 * logk) * dt)
    env = np.exp(-ZETA * T)
    sag = amp * np.exp(-logk)  # a softer body sags more
    return sag - sag * env * np.cos(phase) if kind == "drop" else amp * env * np.cos(phase)


def _truth(kinds_amps, law):
    """Observed signals: law(running max of |x| over the recordings and time, current |x|) ->
    log stiffness, solved by a fixed-point pass (the stiffness depends on the motion)."""
    out, prev = [], 0.0
    for kind, amp in kinds_amps:
        logk = np.zeros_like(T)
        for _ in range(6):
            x = _motion(kind, amp, logk)
            run = np.maximum(np.maximum.accumulate(np.abs(x)), prev)
            logk = law(run, np.abs(x))
        prev = float(run[-1])
        out.append((kind, amp, x))
    return out


def _world(monkeypatch, kinds_amps, law, seed=0):
    rng = np.random.default_rng(seed)
    recs, strains = [], []
    for kind, amp, x in _truth(kinds_amps, law):
        data = x + rng.normal(0, SIGMA, len(T))
        markers = np.stack([data, np.zeros_like(T), np.zeros_like(T)], axis=1)[:, None, :]
        recs.append(SimpleNamespace(times=T, kind=kind, amp=amp, data=data, markers=markers,
                                    marker_rest=np.zeros((1, 3)), seen=np.ones((len(T), 1), bool)))
        strains.append((T[::8], np.abs(x[::8])[:, None]))  # the strain followed from the markers

    def residual(rec, logk):
        r = _motion(rec.kind, rec.amp, logk) - rec.data
        return np.stack([r, np.zeros_like(r), np.zeros_like(r)], axis=1).ravel()

    def rec_residual(problem, ctx, params, shift, late, rec):
        k = float(np.asarray(params.get("stiffness_scale", [0.0]))[0]) + shift
        # a stateless rival: stiffness a function of the current amplitude (either sign)
        s = float(np.asarray(params.get("tension_nonlinearity", [0.0]))[0])
        amp = np.abs(_motion(rec.kind, rec.amp, np.zeros_like(T)) - (rec.amp if rec.kind == "drop" else 0.0))
        return residual(rec, k + late[0] * (T > T[-1] / 2) + s * amp / D_REF)

    def damage_residual(problem, ctx, params, shift, c, bounds, Ds, rec):
        logk = np.zeros_like(T)
        for a, b, D in zip(bounds[:-1], bounds[1:], Ds):
            logk[a:b + 1] = float(np.asarray(params.get("stiffness_scale", [0.0]))[0]) + shift \
                + c * float(np.asarray(D)[0]) / ctx.d_ref
        return residual(rec, logk)

    monkeypatch.setattr(history, "_rec_residual", rec_residual)
    monkeypatch.setattr(history, "_damage_residual", damage_residual)
    monkeypatch.setattr(history.replay, "simulation_times", lambda scene, rec: rec.times)
    problem = SimpleNamespace(train=recs, scene=None, parallel=lambda tasks: [task() for task in tasks])
    ctx = SimpleNamespace(omega=OMEGA, d_ref=D_REF)
    floor = SIGMA**2 * 3 * len(T) * len(recs) * 1.2
    r0 = np.concatenate([rec_residual(problem, ctx, {}, 0.0, (0.0, 0.0), r) for r in recs])
    J = {}
    for name in ("stiffness_scale", "tension_nonlinearity"):
        rp = np.concatenate([rec_residual(problem, ctx, {name: [0.05]}, 0.0, (0.0, 0.0), r) for r in recs])
        J[name] = ((rp - r0) / 0.05)[:, None]
    return problem, ctx, floor, strains, J


def _damage(run, now):  # Mullins-like: softened by the largest strain reached, capped
    return np.log(1.0 - np.minimum(8.0 * run, 0.4))


def _softening(run, now):  # stateless: softer at the current large strain
    return np.log(1.0 - np.minimum(8.0 * now, 0.4))


MOTIONS = [("drop", 0.01), ("drop", 0.01)]  # the same drop twice: only the first loading is virgin


def test_a_body_damaged_by_its_first_loading_is_detected(monkeypatch):
    P, ctx, floor, strains, J = _world(monkeypatch, MOTIONS, _damage)
    monkeypatch.setattr(history, "DAMAGE", False)
    assert not history.check(P, ctx, None, floor, stateless=J, strains=strains)["detected"], \
        "the rule without the damage model misses it (else the test is vacuous)"
    monkeypatch.setattr(history, "DAMAGE", True)
    res = history.check(P, ctx, None, floor, stateless=J, strains=strains)
    assert res["detected"]
    assert res["parameters"]["damage_log_stiffness_per_strain"] < 0


def test_a_stateless_softening_is_not_damage(monkeypatch):
    monkeypatch.setattr(history, "DAMAGE", True)
    for motions in (MOTIONS, [("drop", 0.01), ("drop", 0.012)], [("release", 0.02), ("drop", 0.01)]):
        P, ctx, floor, strains, J = _world(monkeypatch, motions, _softening)
        assert not history.check(P, ctx, None, floor, stateless=J, strains=strains)["detected"]


def test_decide_damage():
    n, dof, floor = 400.0, 1, 0.01
    assert history.decide_damage(0.05, 0.025, 0.05, -0.1, n, dof, floor)
    assert not history.decide_damage(0.05, 0.025, 0.05, 0.1, n, dof, floor)  # stiffening: not damage
    assert not history.decide_damage(0.05, 0.035, 0.05, -0.1, n, dof, floor)  # explains < half the excess
    assert not history.decide_damage(0.05, 0.025, 0.035, -0.1, n, dof, floor)  # its twin gains > half


def test_families_after_history_keep_their_parameters_in_the_gap():
    # a verdict led by history_dependence (outside the library): the tension nonlinearity's
    # cumulative held-out gap must use its own fitted parameters (it was computed without them)
    from matlearn.diagnosis import pipeline

    params = {"tension_nonlinearity": [0.3], pipeline.NUISANCE: [0.1], "stiffness_scale": [0.2]}
    got = pipeline._cumulative_params(["history_dependence", "tension_nonlinearity"], params)
    assert got == {"tension_nonlinearity": {"tension_nonlinearity": [0.3], pipeline.NUISANCE: [0.1]}}
    got = pipeline._cumulative_params(["stiffness_scale", "tension_nonlinearity"], params)
    assert got["stiffness_scale"] == {"stiffness_scale": [0.2], pipeline.NUISANCE: [0.1]}
    assert got["tension_nonlinearity"] == params
