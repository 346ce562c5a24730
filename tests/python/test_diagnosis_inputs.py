"""The input side of `diagnose`: recordings not at the simulation rate, few markers, a held-out
recording with another length and other markers, frames before the markers are first seen all
work; recordings it cannot use fail early with an error naming the recording and the problem."""
import json

import numpy as np
import pytest

from matlearn import meshes
from matlearn.diagnosis import diagnose
from matlearn.diagnosis.problem import Problem, usable_recording
from matlearn.materials import Damping, Material
from matlearn.recording import Recording, load_recording, save_recording
from matlearn.scene import Scene
from matlearn.synthetic import Motion, make_case

from diagnosis_cases import E0, FAST, L, W


def _scene():
    return Scene(meshes.bar(L, W, W, (5, 2, 2)), Material("corotated", E0, 0.4, 1000.0))


def _rec(T=20, K=4, at_rest=False):
    rng = np.random.default_rng(0)
    V = np.asarray(meshes.bar(L, W, W, (5, 2, 2)).vertices)
    rest = V[rng.choice(np.flatnonzero(V[:, 0] > 0.5 * L), K, replace=False)]
    t = 0.0037 * np.arange(T)  # not a multiple of any usual time step
    return Recording(times=t, marker_rest=rest, markers=np.repeat(rest[None], T, axis=0),
                     at_rest_initially=at_rest)


def test_markers_in_other_units_are_named():
    rec = _rec()
    rec_mm = Recording(times=rec.times, marker_rest=rec.marker_rest * 1000, markers=rec.markers * 1000)
    with pytest.raises(ValueError, match=r"train recording a\.npz: marker \d+.*units"):
        usable_recording(rec_mm, _scene(), "train recording a.npz")
    assert usable_recording(rec, _scene(), "x") is rec  # a good recording is passed through


def test_frames_before_the_markers_are_seen_are_dropped_unless_at_rest():
    rec = _rec()
    rec.markers[:3] = np.nan
    out = usable_recording(rec, _scene(), "x")
    np.testing.assert_array_equal(out.times, rec.times[3:])
    np.testing.assert_array_equal(out.markers, rec.markers[3:])
    # a recording that says it starts at rest keeps its first frames (its initial state is known)
    rest = _rec(at_rest=True)
    rest.markers[:3] = np.nan
    assert usable_recording(rest, _scene(), "x").num_frames == rest.num_frames


@pytest.mark.parametrize("seen_frames", [0, 1])
def test_a_recording_without_a_motion_is_named(seen_frames):
    rec = _rec()
    rec.markers[seen_frames:] = np.nan
    with pytest.raises(ValueError, match=r"test recording b\.npz: .*(no marker is seen|at least 2)"):
        usable_recording(rec, _scene(), "test recording b.npz")


def test_stressed_inputs_still_find_a_withheld_stiffness(tmp_path):
    """Markers at 300 Hz with a 1 ms time step, 10 % of the surface tracked, a held-out
    recording longer than the train ones and tracking a third of their markers, and a train
    recording whose markers are unseen in its first frames."""
    cells = (5, 2, 2)
    tip = [[0.75 * L, -1, -1], [1, 1, 1]]
    motions = [
        Motion("release", "train", 0.1, load={"box": tip, "force": [0, -0.25, 0.1]}),
        Motion("release", "train", 0.1, twist={"box": tip, "torque": [0.004, 0, 0]}),
        Motion("release", "test", 0.17, load={"box": tip, "force": [0.05, 0.15, -0.2]}),
    ]
    scene = make_case(tmp_path, "stressed", meshes.bar(L, W, W, tuple(2 * c for c in cells)),
                      Material("corotated", 1.5 * E0, 0.4, 1000.0), Damping(0, 0.002),
                      meshes.bar(L, W, W, cells), Material("corotated", E0, 0.4, 1000.0),
                      Damping(0, 0.002), [[-1, -1, -1], [1e-6, 1, 1]], motions,
                      marker_fraction=0.1, noise=1e-6, seed=0, frame_rate=300.0)
    case = scene.parent
    test = load_recording(case / "test_0.npz")
    save_recording(Recording(times=test.times, marker_rest=test.marker_rest[::3],
                             markers=test.markers[:, ::3]), case / "test_0.npz")
    train = load_recording(case / "train_1.npz")
    train.markers[:2] = np.nan
    save_recording(train, case / "train_1.npz")
    P = Problem(scene)
    assert P.train[1].times[0] == pytest.approx(train.times[2])
    assert P.test[0].num_frames > P.train[0].num_frames
    result = diagnose(scene, tmp_path / "out", progress=lambda m: None, **FAST)
    assert result["verdict"][:1] == ["stiffness_scale"]
    d = json.loads((tmp_path / "out" / "diagnosis.json").read_text(),
                   parse_constant=lambda c: pytest.fail(f"non-standard JSON {c}"))
    e = next(e for e in d["effects"] if e["name"] == "stiffness_scale")
    assert e["gap_after"]["max_error_pct"] < d["gap_before"]["max_error_pct"]
