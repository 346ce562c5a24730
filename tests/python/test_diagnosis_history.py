"""The history-dependence statistic (diagnosis/history.py) on synthetic residuals: the simulated
marker residual of a recording is replaced by an analytic damped oscillation, so the whole
decision (history model fit, stateless rivals refitted, the cut / BIC / rival criteria) runs in
milliseconds. A body that changed between recordings is detected; a stateless body whose
recordings differ through a missed function of the state (an amplitude-dependent stiffness, a
missed damping) is not, although the history model fits it well too."""
from types import SimpleNamespace

import numpy as np
import pytest

from matlearn.diagnosis import history

T = np.linspace(0.0, 0.3, 240)
OMEGA = 60.0
SIGMA = 2e-4  # marker noise (object-size units)


def _signal(amp, log_k, late_k=0.0, zeta=1.0, late_zeta=0.0, stiffening=0.0):
    """Free decay of one mode: frequency OMEGA sqrt(k) exp(stiffening * amp / 0.05) (a
    dimensionless amplitude-dependent stiffness, like the library's families), the second half
    with its own stiffness / damping shift (phase and amplitude continuous)."""
    late = T > T[-1] / 2
    w = OMEGA * np.exp(0.5 * (log_k + late_k * late) + stiffening * amp / 0.05)
    z = zeta + late_zeta * late
    dt = np.diff(T, prepend=0.0)
    return amp * np.exp(-np.cumsum(z * dt)) * np.cos(np.cumsum(w * dt))


def _world(monkeypatch, truths, seed=0):
    """A fake problem whose recording k has the observed signal truths[k] (+ noise); the model
    residual follows `history._rec_residual`'s contract (params, shared shift, late pair)."""
    rng = np.random.default_rng(seed)
    recs = []
    for kw in truths:
        kw = dict(kw)
        offset = kw.pop("offset", 0.0)  # a permanent set: the motion about a shifted equilibrium
        data = _signal(**kw) + offset + rng.normal(0, SIGMA, len(T))
        # one marker moving along x (the residual layout of problem.stack_residuals)
        markers = np.stack([data, np.zeros_like(T), np.zeros_like(T)], axis=1)[:, None, :]
        recs.append(SimpleNamespace(times=T, amp=kw["amp"], data=data, markers=markers,
                                    marker_rest=np.zeros((1, 3)), seen=np.ones((len(T), 1), bool)))

    def rec_residual(problem, ctx, params, shift, late, rec):
        k = float(np.asarray(params.get("stiffness_scale", [0.0]))[0]) + shift
        z = 1.0 + 10.0 * float(np.asarray(params.get("rayleigh_damping", [0.0]))[0])
        s = float(np.asarray(params.get("tension_nonlinearity", [0.0]))[0])
        r = _signal(rec.amp, k, late[0], z, 10.0 * late[1], stiffening=s) - rec.data
        return np.stack([r, np.zeros_like(r), np.zeros_like(r)], axis=1).ravel()

    monkeypatch.setattr(history, "_rec_residual", rec_residual)
    problem = SimpleNamespace(train=recs, parallel=lambda tasks: [task() for task in tasks])
    ctx = SimpleNamespace(omega=OMEGA)
    # linearised sensitivities of the stateless families at the nominal model
    r0 = np.concatenate([rec_residual(problem, ctx, {}, 0.0, (0.0, 0.0), r) for r in recs])
    J = {}
    for name in ("stiffness_scale", "rayleigh_damping", "tension_nonlinearity"):
        rp = np.concatenate([rec_residual(problem, ctx, {name: [0.05]}, 0.0, (0.0, 0.0), r) for r in recs])
        J[name] = ((rp - r0) / 0.05)[:, None]
    floor = SIGMA**2 * len(r0) * 1.2
    return problem, ctx, J, floor


def test_a_body_softened_between_recordings_is_detected(monkeypatch):
    P, ctx, J, floor = _world(monkeypatch, [dict(amp=0.03, log_k=0.0), dict(amp=0.03, log_k=np.log(0.85))])
    res = history.check(P, ctx, None, floor, stateless=J)
    assert res["detected"]
    assert res["parameters"]["recording_stiffness_scales"][0] == pytest.approx(0.85, abs=0.02)


def test_a_permanent_set_is_detected(monkeypatch):
    # the same stiffness, but the second recording oscillates about a shifted equilibrium: no
    # stateless model (they share one equilibrium) nor a stiffness shift can fit it
    P, ctx, J, floor = _world(monkeypatch, [dict(amp=0.03, log_k=0.0), dict(amp=0.03, log_k=0.0, offset=0.006)])
    assert history.check(P, ctx, None, floor, stateless=J)["detected"]
    # the offsets are separable from the oscillation only over a few periods
    short = SimpleNamespace(omega=OMEGA / 4)
    assert not history.check(P, short, None, floor, stateless=J)["detected"]


def test_an_amplitude_dependent_stiffness_is_not_history(monkeypatch):
    # two amplitudes, one stateless stiffening: the history model's per-recording stiffness fits
    # it as well as the stateless family does, with more parameters
    P, ctx, J, floor = _world(monkeypatch, [dict(amp=0.01, log_k=0.0, stiffening=0.15),
                                            dict(amp=0.05, log_k=0.0, stiffening=0.15)])
    res = history.check(P, ctx, None, floor, stateless=J)
    assert res["explained"] > 0.8, "the history model must fit it (else the test is vacuous)"
    assert not res["detected"]


def test_a_missed_damping_is_not_history(monkeypatch):
    # the late-half damping shift of the history model absorbs much of a missed damping
    P, ctx, J, floor = _world(monkeypatch, [dict(amp=0.03, log_k=0.0, zeta=4.0),
                                            dict(amp=0.02, log_k=0.0, zeta=4.0)])
    res = history.check(P, ctx, None, floor, stateless=J)
    assert res["explained"] > 0.4
    assert not res["detected"]
    # without the stateless rivals the same data would be taken for history: the rival test is
    # what decides
    assert history.check(P, ctx, None, floor, stateless=None)["detected"]


def test_decide_needs_the_cut_the_criterion_and_every_rival():
    n, K, floor = 400.0, 2, 0.01
    assert history.decide(1.0, 0.2, {}, n, 1, K, floor)[0]
    assert not history.decide(1.0, 0.7, {}, n, 1, K, floor)[0]  # cut to 0.7 only
    assert not history.decide(1.0, 0.2, {"a": (0.19, 2)}, n, 1, K, floor)[0]  # a rival fits better
    # a rival slightly worse but with fewer parameters wins on BIC
    assert not history.decide(1.0, 0.2, {"a": (0.2001, 1)}, n, 1, K, floor)[0]
    ok, best = history.decide(1.0, 0.2, {"a": (0.5, 2), "b": (0.4, 1)}, n, 1, K, floor)
    assert ok and best == "b"
