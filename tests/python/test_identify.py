"""Whether the recordings determine a learned model's stress scale (learning/identify.py,
`matlearn learn`'s check and `matlearn simulate --model`'s warning)."""
import json
from dataclasses import replace

import numpy as np
import pytest

from matlearn import cli
from matlearn.learning import stress_scale_check
from matlearn.learning.identify import VISIBLE, with_stress_factor
from matlearn.materials import Damping
from matlearn.replay import initial_state, simulate_recording
from matlearn.scene import load_scene

from learning_cases import driven_bar, small_bar_case


def density_scaled(scene, material=None, damping=None):
    return lambda f: scene.model(material=with_stress_factor(material or scene.material, f), damping=damping)


def test_density_over_a_factor_is_every_stress_times_it(tmp_path):
    """The check's premise: with gravity the only external force, a model with its density / f
    moves exactly like the model with its modulus (hence every stress, the stiffness damping
    included) x f; the mass damping acts on both alike."""
    scene = load_scene(small_bar_case(tmp_path))
    mat, damp, f = scene.material, Damping(3.0, 0.004), 2.5
    rec = scene.recordings_with_role("train")[0]
    state = initial_state(scene, scene.model(damping=damp), rec)
    stiff = simulate_recording(scene, scene.model(material=replace(mat, youngs_modulus=f * mat.youngs_modulus),
                                                  damping=damp), rec, state=state)[1]
    light = simulate_recording(scene, density_scaled(scene, damping=damp)(f), rec, state=state)[1]
    plain = simulate_recording(scene, scene.model(damping=damp), rec, state=state)[1]
    moved = np.abs(plain - plain[0]).max()
    assert np.abs(stiff - plain).max() > 0.2 * moved  # the factor matters here
    assert np.abs(stiff - light).max() < 1e-6 * moved


def test_a_release_determines_the_stress_scale_and_a_slow_drive_does_not(tmp_path):
    released = load_scene(small_bar_case(tmp_path / "a"))
    c = stress_scale_check(released, density_scaled(released))
    # the nominal model is 1.75x too stiff (3.5e5 against the truth's 2e5 Pa): the check finds
    # the recordings' scale at the grid point nearest 1 / 1.75, sharply
    assert c["determined"] and c["best_factor"] == 0.5, c
    rms = dict(zip(c["factors"], c["rms_error_pct"]))
    assert rms[0.25] > 5 * rms[0.5] and rms[1.0] > 2.5 * rms[0.5], c
    assert "not the model's own" in c["message"]
    truth = replace(released.material, model="neo_hookean", youngs_modulus=2e5)
    c = stress_scale_check(released, density_scaled(released, truth))
    assert c["determined"] and c["best_factor"] == 1.0, c
    driven = load_scene(driven_bar(tmp_path / "b"))
    c = stress_scale_check(driven, density_scaled(driven))
    assert not c["determined"], c
    assert max(c["rms_error_pct"]) < 0.03, c  # % of the size: the motion is the drive's at any scale
    assert "do not determine" in c["message"]
    # gravity across the bar makes the scale visible again (the sag depends on it)
    sagging = load_scene(driven_bar(tmp_path / "c", gravity=(0.0, 0.0, -9.81 * 40)))
    assert stress_scale_check(sagging, density_scaled(sagging))["determined"]
    with pytest.raises(ValueError, match="one >= 2"):
        stress_scale_check(driven, density_scaled(driven), factors=(0.5, 1.5))


def test_the_check_names_the_recordings_that_carry_the_scale(tmp_path):
    """A release and a slow drive together: the pair determines the scale, and the check says
    that the release does so on its own while the drive leaves it free (from the same replays)."""
    mixed = load_scene(driven_bar(tmp_path / "m", release_first=True))
    c = stress_scale_check(mixed, density_scaled(mixed))
    assert c["determined"] and c["best_factor"] == 0.5, c
    # ... although the pooled errors alone would not say so: the drive's motion raises the bar
    rms = dict(zip(c["factors"], c["rms_error_pct"]))
    assert rms[2.0] - rms[0.5] < VISIBLE * c["motion_rms_pct"], c
    release, drive = c["recordings"]
    assert (release["file"], release["determined"], release["best_factor"]) == ("train_0.npz", True, 0.5), c
    assert drive["file"] == "train_1.npz" and not drive["determined"], c
    assert max(drive["rms_error_pct"]) < 0.03 < min(release["rms_error_pct"]), c
    assert "on its own train_0.npz (x0.5) determines it, train_1.npz leaves it free" in c["message"]
    # the pooled errors are the samples' rms over the recordings' errors
    n = [np.isfinite(rec.markers[..., 0]).sum() for rec in mixed.recordings_with_role("train")]
    pooled = np.sqrt((n[0] * np.square(release["rms_error_pct"]) + n[1] * np.square(drive["rms_error_pct"]))
                     / sum(n))
    assert np.allclose(pooled, c["rms_error_pct"], rtol=1e-9), c
    driven = load_scene(driven_bar(tmp_path / "d"))
    one = stress_scale_check(driven, density_scaled(driven))
    assert len(one["recordings"]) == 1 and "on its own" not in one["message"]


def test_learn_reports_an_undetermined_scale_and_simulate_warns_off_its_recordings(tmp_path, capsys):
    case = driven_bar(tmp_path / "cases")
    run = tmp_path / "run"
    assert cli.main(["learn", str(case), "--out", str(run), "--iterations", "1", "--modes", "8",
                     "--centers", "8", "--no-distill", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "warning: the train recordings do not determine the stress scale" in err
    summary = json.loads((run / "summary.json").read_text())
    assert summary["stress_scale"]["determined"] is False
    assert json.loads((run / "model.json").read_text())["stress_scale_determined"] is False
    # a replay of its own recordings: no warning; a free motion or another object: warned
    assert cli.main(["simulate", str(case), "--model", str(run), "--replay", "0",
                     "--out", str(tmp_path / "replay.npz"), "--quiet"]) == 0
    assert "stress scale" not in capsys.readouterr().err
    other = small_bar_case(tmp_path / "other")
    assert cli.main(["simulate", str(other), "--model", str(run), "--replay", "0",
                     "--out", str(tmp_path / "other.npz"), "--quiet"]) == 0
    assert "is of another scene" in capsys.readouterr().err
    assert cli.main(["simulate", str(case), "--model", str(run), "--duration", "0.05",
                     "--out", str(tmp_path / "free.npz"), "--quiet"]) == 0
    assert "is not a replay of its recordings" in capsys.readouterr().err


def test_simulate_warning_follows_the_runs_metadata(tmp_path):
    from matlearn.commands.simulate import warn_stress_scale

    own, other = tmp_path / "scene.toml", tmp_path / "other.toml"

    def warning(meta, scene, replaying):
        (tmp_path / "model.json").write_text(json.dumps({"scene": str(own), **meta}))
        return warn_stress_scale(tmp_path, scene, replaying)

    free = {"stress_scale_determined": False, "stress_scale_message": "x0.5-x4 alike"}
    assert warning({"stress_scale_determined": True}, other, False) is None
    assert warning({}, other, False) is None  # runs from before the check: nothing to say
    assert warning(free, own, True) is None
    assert "is not a replay" in warning(free, own, False) and "x0.5-x4 alike" in warning(free, own, False)
    assert "is of another scene" in warning(free, other, True)
    assert "start_nominal's model" in warning({**free, "transfer_model": "start_nominal"}, other, True)
    assert "start_nominal" not in warning({**free, "transfer_model": "start_nominal"}, own, False)


def test_a_scale_fixed_within_a_bounded_span_is_called_loose(monkeypatch):
    """The rms errors of a cloud-tracked release shorter than a period (new-user walkthrough): the
    lowest at x2, x1 within 2x of it. The scale is fixed to x1..x2, not left free: the message
    says so instead of 'do not determine'."""
    from matlearn.learning import identify

    rms = {0.25: 2.41, 0.5: 1.88, 1.0: 1.07, 2.0: 0.687, 4.0: 3.16}
    monkeypatch.setattr(identify, "_marker_recordings", lambda scene, role: [("cloud.npz", None)])
    monkeypatch.setattr(identify, "_motions", lambda scene, recs, role: (5.38, [5.38]))
    monkeypatch.setattr(identify, "_replay_rms", lambda scene, f, role, n: (rms[f], [rms[f]]))
    c = stress_scale_check(None, lambda f: f, factors=(0.25, 0.5, 2.0, 4.0))
    assert not c["determined"] and c["best_factor"] == 2.0
    assert c["message"].startswith("the train recordings fix the stress scale only loosely: every stress "
                                   "scaled from x1 to x2 keeps the train rms error near its lowest, which is at x2")
    rms[0.25] = 0.7  # flat down to the grid's end: free, not loose
    c = stress_scale_check(None, lambda f: f, factors=(0.25, 0.5, 2.0, 4.0))
    assert "do not determine the stress scale: with every stress scaled from x0.25 or less to x2" in c["message"]
