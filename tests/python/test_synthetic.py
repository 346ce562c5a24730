"""Synthetic cases with known truth: loads, drives, markers, files; replay of the truth is exact."""
import json

import numpy as np
import pytest

from matlearn import meshes, replay
from matlearn.materials import Damping, Material
from matlearn.recording import load_recording
from matlearn.scene import load_scene
from matlearn.synthetic import Motion, drive_displacement, hold_forces, make_case

CLAMP = [[-1, -1, -1], [1e-3, 1, 1]]
TIP = [[0.199, -1, -1], [1, 1, 1]]
KEYS = [(0.0, [0, 0, 0]), (0.02, [0, 0.01, 0]), (0.05, [0, -0.005, 0.002])]
MOTIONS = [
    Motion("release", "train", 0.05, load={"box": TIP, "force": [0, 0.5, 0]}),
    Motion("release", "test", 0.05, twist={"box": TIP, "torque": [0.005, 0, 0]}),
    Motion("drive", "test", 0.05, drive={"box": TIP, "keyframes": KEYS}),
]


def test_drive_displacement_eases_through_keyframes():
    t = np.array([-1.0, 0.0, 0.02, 0.05, 0.3])
    d = drive_displacement(KEYS, t)
    np.testing.assert_allclose(d, [KEYS[0][1], KEYS[0][1], KEYS[1][1], KEYS[2][1], KEYS[2][1]], atol=1e-15)
    eps = 1e-7  # zero velocity at the keyframes, nonzero between
    for tk in (0.0, 0.02, 0.05):
        v = (drive_displacement(KEYS, [tk + eps]) - drive_displacement(KEYS, [tk - eps])) / (2 * eps)
        assert np.abs(v).max() < 1e-4
    mid = (drive_displacement(KEYS, [0.01 + eps]) - drive_displacement(KEYS, [0.01 - eps])) / (2 * eps)
    assert mid[0, 1] == pytest.approx(np.pi / 2 * 0.01 / 0.02, rel=1e-5)  # half-cosine peak speed


def test_hold_forces_total_force_and_moment():
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(4, 2, 2))
    mass = np.random.default_rng(0).uniform(0.5, 2.0, mesh.num_vertices)  # uneven on purpose
    tip = np.flatnonzero(mesh.vertices[:, 0] >= 0.199)
    f = hold_forces(mesh, mass, Motion(load={"box": TIP, "force": [1.0, -2.0, 0.5]}))
    np.testing.assert_allclose(f.sum(0), [1.0, -2.0, 0.5])
    np.testing.assert_allclose(f[tip], np.outer(mass[tip] / mass[tip].sum(), [1.0, -2.0, 0.5]))
    torque = np.array([0.03, -0.01, 0.02])
    f = hold_forces(mesh, mass, Motion(twist={"box": TIP, "torque": torque}))
    assert np.all(f[np.setdiff1d(np.arange(mesh.num_vertices), tip)] == 0)
    c = (mass[tip, None] * mesh.vertices[tip]).sum(0) / mass[tip].sum()
    np.testing.assert_allclose(f.sum(0), 0, atol=1e-12)
    np.testing.assert_allclose(np.cross(mesh.vertices[tip] - c, f[tip]).sum(0), torque, atol=1e-12)


def test_motion_validation():
    with pytest.raises(ValueError, match="kind"):
        Motion("poke")
    with pytest.raises(ValueError, match="drive"):
        Motion("drive")
    with pytest.raises(ValueError, match="increasing"):
        Motion("drive", drive={"box": TIP, "keyframes": [(0.1, [0, 0, 0]), (0.1, [0, 0, 1])]})
    with pytest.raises(ValueError, match="force"):
        Motion(load={"box": TIP})


@pytest.fixture(scope="module")
def same_mesh_case(tmp_path_factory):
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(6, 1, 1))
    mat, damp = Material(youngs_modulus=2e5), Damping(alpha_stiffness=0.005)
    out = tmp_path_factory.mktemp("cases")
    path = make_case(out, "same", mesh, mat, damp, mesh, mat, damp, CLAMP, MOTIONS, seed=4)
    return path, mesh


def test_truth_replayed_with_the_truth_model_is_exact(same_mesh_case):
    path, _ = same_mesh_case
    scene = load_scene(path)
    assert [r for _, r in scene.recordings] == ["train", "test", "test"]
    model = scene.model()
    for rp, _ in scene.recordings:
        rec = load_recording(rp)
        err = replay.trajectory_error(replay.predict_markers(scene, model, rec), rec, scene.object_size)
        assert err["max_error_pct"] < 1e-6, rp.name
        # ... and the motion is real: markers move by more than 1 % of the object size.
        assert np.nanmax(np.linalg.norm(rec.markers - rec.marker_rest, axis=2)) > 0.01 * scene.object_size


def test_case_files_and_truth(same_mesh_case):
    path, mesh = same_mesh_case
    d = path.parent
    truth = json.loads((d / "truth.json").read_text())
    assert truth["truth_material"]["youngs_modulus"] == 2e5 and truth["seed"] == 4
    assert [r["file"] for r in truth["recordings"]] == ["train_0.npz", "test_0.npz", "test_1.npz"]
    train, drive = load_recording(d / "train_0.npz"), load_recording(d / "test_1.npz")
    assert not train.at_rest_initially and drive.at_rest_initially
    assert drive.has_drive and not train.has_drive
    np.testing.assert_allclose(drive.drive[:, :, 1] - drive.drive_rest[None, :, 1],
                               np.repeat(drive_displacement(KEYS, drive.times)[:, 1:2], len(drive.drive_rest), 1))
    # Markers are truth surface vertices, in a seeded random subset.
    ids = np.array(truth["marker_truth_vertices"])
    np.testing.assert_array_equal(train.marker_rest, mesh.vertices[ids])
    assert set(ids) <= set(meshes.surface_vertices(mesh))


def test_discretisation_gap_sparse_noisy_markers(tmp_path):
    truth_mesh = meshes.bar(0.2, 0.04, 0.04, cells=(8, 2, 2))
    model_mesh = meshes.bar(0.2, 0.04, 0.04, cells=(4, 1, 1))
    mat, damp = Material(youngs_modulus=2e5), Damping(alpha_stiffness=0.005)
    motions = [Motion("release", "test", 0.04, load={"box": TIP, "force": [0, 0.5, 0]})]
    kw = dict(marker_fraction=0.25, noise=1e-4, dropout=0.2, frame_rate=300.0, seed=7)
    p1 = make_case(tmp_path, "a", truth_mesh, mat, damp, model_mesh, mat, damp, CLAMP, motions, **kw)
    p2 = make_case(tmp_path, "b", truth_mesh, mat, damp, model_mesh, mat, damp, CLAMP, motions, **kw)
    r1, r2 = load_recording(p1.parent / "test_0.npz"), load_recording(p2.parent / "test_0.npz")
    np.testing.assert_array_equal(r1.markers, r2.markers)  # seeded: identical
    n_surf = len(meshes.surface_vertices(truth_mesh))
    assert r1.num_markers == round(0.25 * n_surf)
    np.testing.assert_allclose(r1.times, np.arange(13) / 300.0)
    assert 0.05 < 1 - r1.seen.mean() < 0.35
    scene = load_scene(p1)
    assert scene.mesh.num_tets == model_mesh.num_tets
    err = replay.trajectory_error(replay.predict_markers(scene, scene.model(), r1), r1, scene.object_size)
    # The coarse mesh is stiffer than the truth: a gap, but not a wrong setup.
    assert 0.05 < err["max_error_pct"] < 5.0


def test_make_case_errors(tmp_path):
    m = meshes.bar(cells=(2, 1, 1))
    mat, damp = Material(), Damping()
    with pytest.raises(ValueError, match="at least one Motion"):
        make_case(tmp_path, "x", m, mat, damp, m, mat, damp, CLAMP, [])
    with pytest.raises(ValueError, match="marker_fraction"):
        make_case(tmp_path, "x", m, mat, damp, m, mat, damp, CLAMP, MOTIONS, marker_fraction=0)
    with pytest.raises(ValueError, match="contains no vertex"):
        make_case(tmp_path, "x", m, mat, damp, m, mat, damp, [[5, 5, 5], [6, 6, 6]], MOTIONS)
