"""The history check's piecewise simulations (history._segments): models switched along a
recording, the state carried across. One model over every segment is the problem's own
prediction (same start state, same linearised step); two models agree with the scene's
integrator (one Newton iteration per step), drive points included."""
import numpy as np
import pytest

from matlearn import replay
from matlearn.diagnosis import history
from matlearn.diagnosis.effects import EffectContext, build_model
from matlearn.diagnosis.problem import Problem

from diagnosis_cases import tiny_case
from learning_cases import driven_bar


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    return tiny_case(tmp_path_factory.mktemp("seg"), "seg", E_scale=1.2, seed=2)


@pytest.fixture(scope="module")
def driven(tmp_path_factory):
    return driven_bar(tmp_path_factory.mktemp("segd"))


def _two_models(P):
    s = P.scene
    ctx = EffectContext(s.mesh, s.material, s.damping, s.fixed)
    return build_model(ctx, {"stiffness_scale": [0.0]}), build_model(ctx, {"stiffness_scale": [0.4]})


def _bounds(P, rec):
    n = len(replay.simulation_times(P.scene, rec))
    return [0, n // 3, n - 1]


def test_one_model_over_every_segment_is_the_prediction_started_in_motion(bar):
    P = Problem(bar, estimate_velocity=True)
    rec = P.train[0]
    rec.at_rest_initially = False  # so the start velocity is estimated from the markers
    m, _ = _two_models(P)
    assert np.abs(P.start_state(m, rec)[1]).max() > 0  # the start does move
    np.testing.assert_allclose(history._segments(P, [m, m], _bounds(P, rec), rec), P.predict(m, rec),
                               rtol=0, atol=1e-9 * P.object_size)


@pytest.mark.parametrize("case", ["bar", "driven"])
def test_switched_models_agree_with_the_integrator(case, request):
    scene = request.getfixturevalue(case)
    fast, slow = Problem(scene), Problem(scene, reuse_factor=False)
    for P in (fast, slow):
        assert P.fast_newton == 1
    rec, rec_slow = fast.train[0], slow.train[0]
    assert rec.has_drive == (case == "driven")
    a = history._segments(fast, list(_two_models(fast)), _bounds(fast, rec), rec)
    b = history._segments(slow, list(_two_models(slow)), _bounds(slow, rec_slow), rec_slow)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * fast.object_size)
    # the switch matters: the first model alone moves differently
    m0, _ = _two_models(fast)
    assert np.abs(a - fast.predict(m0, rec)).max() > 1e-5 * fast.object_size
