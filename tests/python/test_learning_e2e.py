"""End to end: learning on a small bar cuts the held-out error; resume gives the same result;
the CLI writes a loadable model, metrics and plots; learned damping stays passive."""
import json

import numpy as np
import pytest

from matlearn import cli
from matlearn.learning import LearnOptions, learn, load_model
from matlearn.embedding import embed_points
from matlearn.learning.loop import code_fingerprint, robust_initial_state
from matlearn.replay import SCORE_START, predict_markers, simulate_recording, trajectory_error
from matlearn.scene import load_scene

from learning_cases import small_bar_case


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    return small_bar_case(tmp_path_factory.mktemp("cases"))


def test_learning_cuts_held_out_error_and_resume_is_identical(case, tmp_path):
    sc = load_scene(case)
    opts = LearnOptions(iterations=2, modes=12, centers=12, ridges=(1e-6,))
    full = learn(sc, tmp_path / "full", opts, log=None)
    nominal = full["nominal"]["test"]["max_error_pct"]
    learned = full["final"]["test"]["max_error_pct"]
    assert nominal > 2.0  # a real gap to close
    # Stated factor: learning cuts the held-out max error by at least 8x.
    print("held-out max error nominal", nominal, "learned", learned)
    assert learned < nominal / 8, (nominal, learned)
    # The learned model, replayed outside the loop, scores the same.
    model = sc.model(full["params"].correction())
    rec = sc.recordings_with_role("test")[0]
    state = robust_initial_state(sc, model, rec, embed_points(sc.mesh, rec.marker_rest), SCORE_START)
    pred = predict_markers(sc, model, rec, sim=simulate_recording(sc, model, rec, state=state))
    assert trajectory_error(pred, rec, sc.object_size)["max_error_pct"] == pytest.approx(learned, rel=1e-9)
    # Kill after the first iteration (simulated by a 1-iteration run), then resume to 2.
    learn(sc, tmp_path / "part", LearnOptions(iterations=1, modes=12, centers=12, ridges=(1e-6,)), log=None)
    resumed = learn(sc, tmp_path / "part", opts, resume=True, log=None)
    a = [m["train"]["max_error_pct"] for m in full["metrics"]]
    b = [m["train"]["max_error_pct"] for m in resumed["metrics"]]
    np.testing.assert_allclose(b, a, rtol=1e-9)
    np.testing.assert_allclose(resumed["params"].weights, full["params"].weights, rtol=1e-9, atol=0)
    # Only the iteration cap may change on a resume: other options shaped the iterations run.
    with pytest.raises(ValueError, match=r"other options \(centers: 12 then, 8 now"):
        learn(sc, tmp_path / "part", LearnOptions(iterations=2, modes=12, centers=8, ridges=(1e-6,)),
              resume=True, log=None)
    # A run written by other code is not resumed: its checkpointed correction would be scored
    # by a different model (bench/visibility.json's markers_13 re-score 0.05295 -> 0.05311 %
    # was a checkpoint of the C1 box extension re-scored with the frozen-kernel extension).
    mfile = tmp_path / "part" / "metrics.json"
    doc = json.loads(mfile.read_text())
    assert doc["code"] == code_fingerprint()
    doc["code"] = "0" * 40
    mfile.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="different code"):
        learn(sc, tmp_path / "part", opts, resume=True, log=None)


def test_cli_writes_model_metrics_and_plots(case, tmp_path):
    out = tmp_path / "run"
    rc = cli.main(["learn", str(case), "--out", str(out), "--iterations", "1", "--modes", "10",
                   "--centers", "8", "--no-distill", "--quiet", "--extend", "3"])
    assert rc == 0
    for name in ("model.npz", "model.json", "metrics.json", "convergence.png", "error_histograms.png"):
        assert (out / name).exists(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["iterations"]) == 2
    assert json.loads((out / "summary.json").read_text())["resumed"] is False
    assert metrics["options"]["extend"] == [3.0]
    steps = [t["step"] for t in metrics["iterations"][0]["fit"]["steps_tried"]]
    assert steps[0] == 1.0 and set(steps[1:]) <= {3.0, *LearnOptions().backtrack}
    corr = load_model(out)
    Fh = np.array([[1.05, 1.0, 0.97]])
    assert np.all(np.isfinite(corr.evaluate(Fh, np.zeros_like(Fh))[0]))
    # A non-empty run folder is not overwritten silently.
    assert cli.main(["learn", str(case), "--out", str(out), "--quiet"]) == 2


def test_learning_with_tangent_damping_cuts_held_out_error_and_saves_the_flag(case, tmp_path):
    sc = load_scene(case)
    opts = LearnOptions(iterations=2, modes=12, centers=12, ridges=(1e-6,), tangent_damping=True)
    res = learn(sc, tmp_path / "td", opts, log=None)
    nominal = res["nominal"]["test"]["max_error_pct"]
    learned = res["final"]["test"]["max_error_pct"]
    assert learned < nominal / 8, (nominal, learned)
    assert res["params"].tangent_damping
    assert res["params"].correction().tangent_damping
