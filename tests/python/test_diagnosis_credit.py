"""The discretisation credit must see the mesh's error: it is measured on the raw residual's
sensitivities (fitting.residual_pair), because the debiased residual has the discrepancy's
direction projected out (fitting.debias) and every family's debiased sensitivity is blind to it."""
from types import SimpleNamespace

import numpy as np
import pytest

from matlearn.diagnosis import fitting, ranking


def _stub(monkeypatch, b, obs):
    """A problem with one recording whose prediction is `obs` plus the model's own offset
    vector (build_model returns the parameters; predict adds them), and the discrepancy b."""
    T = len(obs) // 3
    rec = SimpleNamespace(seen=np.ones((T, 1), bool), markers=np.zeros((T, 1, 3)))
    prob = SimpleNamespace(train=[rec], object_size=1.0, disc_bias={id(rec): b},
                           disc_weight_range=(0.55, 4.0 / 3.0), prefetch=lambda models, recs=None: None)
    monkeypatch.setattr(fitting, "build_model", lambda ctx, params: params)
    monkeypatch.setattr(fitting, "predict",
                        lambda problem, model, rec, fast=True: (obs + model.get("shift", 0.0)).reshape(T, 1, 3))
    return prob


def test_raw_sensitivities_keep_the_direction_the_debiased_ones_lose(monkeypatch):
    rng = np.random.default_rng(3)
    b = rng.standard_normal(30)
    obs = -0.9 * b + 0.01 * rng.standard_normal(30)  # weight 0.9: inside the range
    along = 0.5 * b + 0.05 * rng.standard_normal(30)  # a family that mimics the discrepancy
    prob = _stub(monkeypatch, b, obs)
    r0, raw0 = fitting.residual_pair(prob, None, {})
    r1, raw1 = fitting.residual_pair(prob, None, {"shift": 0.1 * along})
    np.testing.assert_allclose(raw0, obs)
    assert abs(r0 @ b) < 1e-9 * (b @ b)  # debiased: b projected out
    J_deb = ((r1 - r0) / 0.1)[:, None]
    J_raw = ((raw1 - raw0) / 0.1)[:, None]
    np.testing.assert_allclose(J_raw[:, 0], along, atol=1e-12)
    sl = slice(0, 30)
    blind = ranking.discretisation_credit({"f": J_deb}, b, sl, 1.0)["f"]
    seen = ranking.discretisation_credit({"f": J_raw}, b, sl, 1.0)["f"]
    assert blind == pytest.approx(0.0, abs=1e-6 * (b @ b))
    assert seen > 0.9 * (b @ b)


def test_sensitivities_return_the_raw_jacobian_from_the_same_simulations(monkeypatch):
    rng = np.random.default_rng(4)
    b = rng.standard_normal(12)
    obs = -1.0 * b + 0.1 * rng.standard_normal(12)
    prob = _stub(monkeypatch, b, obs)
    calls = []
    monkeypatch.setattr(fitting, "build_model", lambda ctx, params: {"shift": params["stiffness_scale"][0] * b})
    stub_predict = fitting.predict
    monkeypatch.setattr(fitting, "predict", lambda *a, **k: calls.append(1) or stub_predict(*a, **k))
    r0, raw0 = fitting.residual_pair(prob, None, {"stiffness_scale": [0.0]})
    n = len(calls)
    J, J_raw = fitting.sensitivities(prob, None, r0, ["stiffness_scale"], raw0=raw0)
    assert len(calls) - n == 1  # one simulation per parameter for both Jacobians
    np.testing.assert_allclose(J_raw["stiffness_scale"][:, 0], b, atol=1e-9)
    assert np.abs(J["stiffness_scale"]).max() < 1e-9  # pure discrepancy: debiased away
    assert isinstance(fitting.sensitivities(prob, None, r0, ["stiffness_scale"]), dict)
