"""`matlearn diagnose` (the CLI and the Python API) on a scene whose recordings are point clouds only
(formats.md allows them): the clouds are tracked first, as `matlearn learn` does, instead of
stopping with "diagnosis needs at least one 'train' recording with markers"."""
from __future__ import annotations

import numpy as np

from matlearn import _core, meshes
import pytest

from matlearn.diagnosis import pipeline
from matlearn.diagnosis.pipeline import scene_with_markers
from matlearn.materials import Damping, Material, make_model
from matlearn.recording import Recording, load_recording, save_recording
from matlearn.scene import Scene, load_scene, save_scene


def _cloud_scene(tmp_path):
    mesh = meshes.bar(0.1, 0.02, 0.02, (5, 1, 1))
    V = np.asarray(mesh.vertices)
    mat = Material("corotated", 2e5, 0.4, 1000.0)
    fixed = np.flatnonzero(V[:, 0] < 1e-9)
    integ = _core.time.Integrator(make_model(mesh, mat, Damping(0, 0.002)), fixed, 1e-3, np.array([0, -9.81, 0.0]))
    integ.set_state(V.copy(), np.zeros_like(V))
    X, _ = integ.simulate(12, np.zeros_like(V), 1)
    X = np.asarray(X)
    rng = np.random.default_rng(0)
    F = np.asarray(mesh.surface_faces)
    clouds = []
    for x in X:  # 150 random surface points per frame
        f = F[rng.integers(len(F), size=150)]
        b = rng.dirichlet([1, 1, 1], size=150)
        clouds.append(np.einsum("kj,kjd->kd", b, x[f]))
    off = np.arange(len(X) + 1) * 150
    rec = Recording(1e-3 * np.arange(len(X)) + 0.5, cloud_points=np.concatenate(clouds), cloud_offsets=off,
                    cloud_sigma=1e-4, at_rest_initially=True)
    save_recording(rec, tmp_path / "c.npz")
    scene = Scene(mesh, mat, Damping(0, 0.002), fixed, 1e-3, (0, -9.81, 0), [(tmp_path / "c.npz", "train")])
    path = save_scene(scene, tmp_path / "scene.toml")
    return scene, path, rec, X, V


def test_cloud_only_scene_is_tracked_into_markers(tmp_path):
    scene, path, rec, X, V = _cloud_scene(tmp_path)
    assert scene_with_markers(path, tmp_path / "out") != path
    tracked = load_scene(tmp_path / "out" / "tracked" / "scene.toml")
    (p, role), = tracked.recordings
    mrec = load_recording(p)
    assert role == "train" and mrec.num_markers > 0 and mrec.num_frames == len(X)
    np.testing.assert_allclose(mrec.times, rec.times)
    # the tracked markers follow the sag (tip drops ~mm in 12 ms) to a fraction of it
    tip = np.argmax(mrec.marker_rest[:, 0])
    err = np.nanmax(np.abs(mrec.markers[:, tip] - X[:, np.argmin(np.linalg.norm(V - mrec.marker_rest[tip], axis=1))]))
    assert err < 0.5 * np.abs(X[-1] - X[0]).max() + 1e-4
    # a scene with markers is diagnosed as it is
    assert scene_with_markers(tmp_path / "out" / "tracked" / "scene.toml", tmp_path / "out2") == \
        tmp_path / "out" / "tracked" / "scene.toml"

    # a Scene object (the Python API) is tracked the same way, and one with markers kept as it is
    assert scene_with_markers(scene, tmp_path / "out3") == tmp_path / "out3" / "tracked" / "scene.toml"
    marked = load_scene(tmp_path / "out" / "tracked" / "scene.toml")
    assert scene_with_markers(marked, tmp_path / "out4") is marked


def test_python_diagnose_tracks_cloud_only_recordings(tmp_path, monkeypatch):
    """diagnose() from Python diagnoses the tracked scene, as the CLI does (it had skipped
    cloud-only recordings and stopped for want of a train recording with markers)."""
    _, path, _, _, _ = _cloud_scene(tmp_path)
    seen = []

    class Stop(Exception):
        pass

    def problem(scene, **kw):
        seen.append(scene)
        raise Stop

    monkeypatch.setattr(pipeline, "Problem", problem)
    with pytest.raises(Stop):
        pipeline.diagnose(path, tmp_path / "diag", progress=lambda *a: None)
    assert seen == [tmp_path / "diag" / "tracked" / "scene.toml"]
    assert load_recording(load_scene(seen[0]).recordings[0][0]).num_markers > 0
