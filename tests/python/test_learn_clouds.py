"""`learn` on a scanned scene exactly as on markers: a cloud-only train recording (virtual
single-view scans with noise, outliers and dropped frames) is tracked by `learn` itself, cached
in the run folder (a resumed run does not track again), learned with the observation weight
chosen from the scan noise, and the learned model cuts the held-out error (scored on an exact
marker recording of a different load) by a stated factor."""
import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from matlearn import cli, meshes
from matlearn.clouds.prepare import cloud_lambda, track_scene
from matlearn.clouds.scanner import ScanSettings, default_cameras, scan_recording
from matlearn.learning import LearnOptions, learn
from matlearn.materials import Damping, Material
from matlearn.recording import load_recording
from matlearn.scene import load_scene, save_scene
from matlearn.synthetic import Motion, make_case

L = 0.08
NOISE = 2e-4  # m, 0.23 % of the object size


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    root = tmp_path_factory.mktemp("scanned")
    mesh = meshes.bar(L, 0.02, 0.02, cells=(5, 1, 1))
    tip = [[L - 0.011, -1, -1], [1, 1, 1]]
    motions = [Motion("release", "train", 0.1, load={"box": tip, "force": [0, 0.25, 0.08]}),
               Motion("release", "test", 0.1, load={"box": tip, "force": [0, 0.4, -0.05]})]
    path = make_case(root, "bar", mesh, Material("neo_hookean", 2e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     mesh, Material("corotated", 3.5e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     [[-1, -1, -1], [1e-4, 1, 1]], motions, marker_fraction=1.0, frame_rate=500.0, seed=3)
    sc = load_scene(path)
    rec = load_recording(sc.recording_paths("train")[0])
    V = np.asarray(sc.mesh.vertices)
    d, idx = cKDTree(V).query(rec.marker_rest)
    assert d.max() < 1e-9  # dense markers sit on the surface vertices: the true surface
    X = np.repeat(V[None], rec.num_frames, axis=0)
    X[:, idx] = rec.markers
    settings = ScanSettings(noise=NOISE, outlier_fraction=0.01, drop_fraction=0.05, seed=1)
    scan_recording(X, rec.times, np.asarray(sc.mesh.surface_faces), default_cameras(V, 1), settings,
                   path=root / "train_scan.npz", at_rest_initially=rec.at_rest_initially)
    recs = [(root / "train_scan.npz", "train")] + [(p, r) for p, r in sc.recordings if r == "test"]
    return save_scene(replace(sc, recordings=recs), root / "scene.toml")


def test_learn_tracks_clouds_chooses_lambda_and_cuts_held_out_error(scanned, tmp_path):
    sc = load_scene(scanned)
    assert load_recording(sc.recording_paths("train")[0]).num_markers == 0  # clouds only
    opts = LearnOptions(iterations=2, modes=12, centers=12, ridges=(1e-6,))
    res = learn(sc, tmp_path / "run", opts, log=None)
    (info,) = res["tracking"].values()
    assert info["role"] == "train" and not info["cached"]
    # lambda from the scan noise and the motion, below the marker default, as documented.
    rows = res["metrics"][0]["lam"], json.loads((tmp_path / "run" / "metrics.json").read_text())["lambda_choice"]
    (row,) = rows[1]["recordings"]
    # The scanner accuracy stated in the recording, averaged over the points supporting a vertex.
    assert info["sigma_scan_m"] == NOISE and info["points_per_seen_vertex"] > 2
    assert info["sigma_obs_m"] == pytest.approx(NOISE / np.sqrt(info["points_per_seen_vertex"]))
    # Tracked markers average many points: their frame-to-frame noise is far below the scanner's.
    assert 0 < info["tracked_marker_noise_m"] < NOISE / 3
    assert res["lambda"] == pytest.approx(cloud_lambda(row["d_rms_m"], row["omega_s"], info["sigma_obs_m"],
                                                       info["frame_dt_s"], sc.time_step))
    assert 1e-3 < res["lambda"] < 1.0
    nominal = res["nominal"]["test"]["max_error_pct"]
    tests = [m["test"]["max_error_pct"] for m in res["metrics"]]
    learned = res["final"]["test"]["max_error_pct"]
    print("held-out max error per iteration", tests, "lambda", res["lambda"])
    assert nominal > 2.0 and len(tests) == 3
    # Stated factor: two iterations from single-view scans cut the held-out max error (a 1.6x
    # larger load than the train recording's, so its stretches leave the fitted range) by at
    # least 3x (measured 7.8x; other scan-noise seeds 2.2-5x). Before the fit's tangent penalty
    # the second iteration took it to 337 % (fit.py docstring).
    assert learned < nominal / 3, tests
    assert max(tests[1:]) < nominal / 2, tests  # no iteration explodes on the held-out motion
    # The learn loop never accepts an update that raises the train error.
    train = [m["train"]["max_error_pct"] for m in res["metrics"]]
    assert all(b <= a for a, b in zip(train, train[1:])) and train[-1] < train[0] / 3, train
    # Well-conditioned: a 1e-12 relative change of the learned weights moves the held-out
    # error by round-off only (the unregularised fit's model moved by 5 % at 1e-14: chaotic).
    p = res["params"]
    rng = np.random.default_rng(0)
    q = replace(p, weights=p.weights * (1 + 1e-12 * rng.standard_normal(p.weights.shape)))
    test_rec = res["scene"].recordings_with_role("test")
    moved = score_params(res["scene"], q, test_rec)
    assert moved == pytest.approx(learned, rel=1e-6), (moved, learned)
    # Resume: the tracked clouds are reused from the run folder, not tracked again.
    tracked = tmp_path / "run" / "tracked"
    stamp = {p.name: p.stat().st_mtime_ns for p in tracked.iterdir()}
    again = learn(sc, tmp_path / "run", opts, resume=True, log=None)
    assert all(v["cached"] for v in again["tracking"].values())
    assert {p.name: p.stat().st_mtime_ns for p in tracked.iterdir()} == stamp
    assert again["final"]["test"]["max_error_pct"] == pytest.approx(learned, rel=1e-9)


def score_params(scene, params, recs):
    """Max held-out marker error (% of size) of a correction on recordings `recs`, scored like the
    loop's test errors (from replay.SCORE_START)."""
    from matlearn.embedding import embed_points
    from matlearn.learning.loop import _errors
    from matlearn.replay import SCORE_START

    errs, _ = _errors(scene, scene.model(params.correction()), recs,
                      [embed_points(scene.mesh, r.marker_rest) for r in recs], start=SCORE_START)
    return max(float(e.max()) for e in errs)


def test_tracking_cache_is_invalidated_when_the_clouds_change(scanned, tmp_path):
    sc = load_scene(scanned)
    new, info = track_scene(sc, tmp_path / "t")
    (v,) = info.values()
    assert not v["cached"] and load_recording(new.recording_paths("train")[0]).num_markers > 0
    assert all(v["cached"] for v in track_scene(sc, tmp_path / "t")[1].values())
    # Same file name, different clouds (another noise seed): tracked again.
    rec = load_recording(sc.recording_paths("train")[0])
    rec.cloud_points = rec.cloud_points + 1e-5
    from matlearn.recording import save_recording

    p = tmp_path / "moved" / "train_scan.npz"
    save_recording(rec, p)

    moved = replace(sc, recordings=[(p, "train")])
    (w,) = track_scene(moved, tmp_path / "t")[1].values()
    assert not w["cached"]


def test_cli_learns_from_a_cloud_scene(scanned, tmp_path):
    out = tmp_path / "cli"
    rc = cli.main(["learn", str(scanned), "--out", str(out), "--iterations", "1", "--modes", "10",
                   "--centers", "8", "--no-distill", "--quiet"])
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["lambda"] < 1.0
    assert summary["final"]["test"]["max_error_pct"] < summary["nominal"]["test"]["max_error_pct"]
    assert any(p.name.endswith("_tracked.npz") for p in (out / "tracked").iterdir())


def test_marker_noise_and_cloud_lambda():
    from matlearn.clouds.prepare import marker_noise
    from matlearn.recording import Recording

    rng = np.random.default_rng(0)
    t = np.arange(400) * 0.005
    K = 30
    rest = rng.standard_normal((K, 3)) * 0.01
    smooth = rest[None] + 1e-3 * np.sin(2 * np.pi * 5.0 * t)[:, None, None]  # 5 Hz at 200 Hz
    noisy = smooth + rng.normal(0.0, 1e-4, smooth.shape)
    noisy[50:60, :5] = np.nan  # unseen stretches are skipped
    est = marker_noise(Recording(t, rest, noisy))
    assert est == pytest.approx(1e-4, rel=0.05)
    assert marker_noise(Recording(t, rest, smooth)) < 2e-6  # a smooth motion is not noise
    # lambda: 1 for exact markers, falls as 1 / sigma (omega_c^2 ~ 1 / sigma), capped at 1.
    lam = [cloud_lambda(1e-3, 50.0, s, 0.005, 1e-3) for s in (0.0, 1e-5, 1e-4, 4e-4)]
    assert lam[0] == 1.0 and cloud_lambda(1e-3, 50.0, 1e-6, 0.005, 1e-3) == 1.0 and lam[1] < 1.0
    assert lam[3] == pytest.approx(lam[2] / 4, rel=1e-9)
    wc = 50.0 * (np.pi * 1e-6 / (50.0 * 1e-8 * 0.005)) ** 0.25
    assert lam[2] == pytest.approx((wc * 1e-3) ** 2, rel=1e-12)


def test_space_time_solve_re_estimates_cloud_correspondences(scanned, tmp_path):
    """refresh_correspondences: the correspondences are re-estimated at the space-time trajectory
    and the solve continues against them (method.md section 7); the result stays as close to the
    true surface as the tracker's correspondences give (measured on this case, 4 Gauss-Newton
    steps: RMS 2.94e-5 m without, 2.99e-5 m with one round, both 7x below the scan noise: not
    better, hence off by default)."""
    from pathlib import Path

    from matlearn.learning.loop import Learner, _errors
    from matlearn.replay import interpolate_frames, simulation_times

    sc = load_scene(scanned)
    truth = load_recording(load_scene(Path(scanned).parent / "bar" / "scene.toml").recording_paths("train")[0])
    idx = cKDTree(np.asarray(sc.mesh.vertices)).query(truth.marker_rest)[1]
    got = {}
    for rounds in (0, 1):
        lrn = Learner(sc, tmp_path / "run", LearnOptions(modes=12, gn_iterations=4, refresh_correspondences=rounds),
                      log=None)
        model = lrn.scene.model()
        _, sims = _errors(lrn.scene, model, lrn.train, lrn.emb_train)
        lrn._choose_lambda(sims)
        _, (X,), (info,) = lrn._spacetime(model, sims, None, 0)
        assert len(info["refresh_costs"]) == rounds
        P = interpolate_frames(simulation_times(lrn.scene, lrn.train[0]), X[:, idx], truth.times)
        got[rounds] = (X, float(np.sqrt(np.mean(np.sum((P - truth.markers) ** 2, axis=2)))))
    (X0, e0), (X1, e1) = got[0], got[1]
    print("space-time RMS vs the true surface: tracker correspondences", e0, "refreshed", e1)
    assert np.abs(X1 - X0).max() > 1e-6  # the refresh moved the trajectory
    assert e0 < NOISE / 3 and e1 < 1.25 * e0
