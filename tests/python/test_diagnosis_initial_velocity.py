"""A recording that does not say it starts at rest starts with the velocity its markers show:
problem.marker_velocity / initial_velocity, used by Problem.predict."""
import numpy as np

from matlearn import meshes
from matlearn.diagnosis.problem import Problem, marker_velocity
from matlearn.materials import Damping, Material
from matlearn.recording import Recording, load_recording, save_recording
from matlearn.synthetic import Motion, make_case

from diagnosis_cases import E0, L, W


def test_marker_velocity_is_the_slope_of_the_motion_not_its_acceleration():
    rng = np.random.default_rng(1)
    K, T, dt = 12, 40, 1e-3
    rest = rng.standard_normal((K, 3)) * 0.01
    u1, u2 = rng.standard_normal((K, 3)), rng.standard_normal((K, 3))
    t = dt * np.arange(T)
    # a constant acceleration from velocity v (pattern u1) plus a slow swing (pattern u2)
    v, a, w = 0.02, 30.0, 20.0
    X = rest + (v * t + 0.5 * a * t**2)[:, None, None] * u1 + 1e-3 * np.sin(w * t)[:, None, None] * u2
    rec = Recording(times=t + 3.0, marker_rest=rest, markers=X)
    est = marker_velocity(rec)
    truth = v * u1 + 1e-3 * w * u2
    np.testing.assert_allclose(est, truth, atol=1e-3 * np.abs(truth).max())
    # a forward difference reads the acceleration as velocity: guards the test itself
    diff = (X[1] - X[0]) / dt
    assert np.abs(diff - truth).max() > 50 * np.abs(est - truth).max()
    # markers unseen in most frames get no estimate
    X2 = X.copy()
    X2[:30, 0] = np.nan
    est2 = marker_velocity(Recording(times=t, marker_rest=rest, markers=X2))
    assert np.isnan(est2[0]).all() and np.isfinite(est2[1:]).all()


def test_a_recording_cut_mid_swing_is_predicted_from_its_moving_start(tmp_path):
    """The nominal model is the truth (same mesh, no noise); the release recording is cut
    after its first swing has started, so it begins moving. Starting at rest (the old initial
    state) leaves a residual no material effect could explain; the estimated velocity does not."""
    bar = meshes.bar(L, W, W, (5, 2, 2))
    mat, dmp = Material("corotated", E0, 0.4, 1000.0), Damping(0, 0.002)
    tip = [[0.75 * L, -1, -1], [1, 1, 1]]
    scene = make_case(tmp_path, "cut", bar, mat, dmp, bar, mat, dmp, [[-1, -1, -1], [1e-6, 1, 1]],
                      [Motion("release", "train", 0.08, load={"box": tip, "force": [0, -0.25, 0.1]})],
                      marker_fraction=0.5, seed=0)
    path = scene.parent / "train_0.npz"
    rec = load_recording(path)
    speed = np.linalg.norm(np.diff(rec.markers, axis=0), axis=2).mean(axis=1)
    k = int(np.argmax(speed[:40]))  # the fastest frame of the first swing
    save_recording(Recording(times=rec.times[k:], marker_rest=rec.marker_rest, markers=rec.markers[k:]), path)
    rss = {}
    for est in (False, True):
        r = Problem(scene, estimate_velocity=est).residual(Problem(scene).scene.model())
        rss[est] = float(r @ r)
    assert rss[True] < 0.1 * rss[False], rss


def test_a_noisy_start_from_rest_gets_no_velocity():
    rng = np.random.default_rng(2)
    K, T, dt, sigma = 30, 200, 1e-3, 3e-5
    rest = rng.standard_normal((K, 3)) * 0.01
    u = rng.standard_normal((K, 3))
    t = dt * np.arange(T)
    # released from rest: accelerates, then swings (about 5 mm); white marker noise
    X = rest + 5e-3 * (1 - np.cos(60 * t))[:, None, None] * u
    noisy = X + rng.normal(0, sigma, X.shape)
    assert np.all(marker_velocity(Recording(times=t, marker_rest=rest, markers=noisy)) == 0.0)
    # the same swing caught mid-way is moving: a clear velocity is kept
    k = 12
    est = marker_velocity(Recording(times=t[k:], marker_rest=rest, markers=noisy[k:]))
    truth = 5e-3 * 60 * np.sin(60 * t[k]) * u
    assert np.linalg.norm(est - truth) < 0.2 * np.linalg.norm(truth)


def test_marker_velocity_relative_to_a_prediction_from_rest():
    """A release from rest whose first frames carry a fast oscillation: the raw marker tracks
    show a 'velocity' (the fit over the first frames averages the fast motion), the same tracks
    relative to a prediction of that start from rest (which carries the fast start, its slow
    acceleration 10 % off) show none; a moving start still shows its velocity beyond it."""
    rng = np.random.default_rng(3)
    K, T, dt, sigma = 30, 120, 1e-3, 2e-5
    rest = rng.standard_normal((K, 3)) * 0.01
    u1, u2 = rng.standard_normal((K, 3)), rng.standard_normal((K, 3))
    t = dt * np.arange(T)
    slow = 4e-3 * (1 - np.cos(40 * t))[:, None, None] * u1
    fast = 4e-4 * (1 - np.cos(900 * t))[:, None, None] * u2
    X = rest + slow + fast + rng.normal(0, sigma, (T, K, 3))
    rec = Recording(times=t, marker_rest=rest, markers=X)
    assert np.abs(marker_velocity(rec)).max() > 0.01  # the old estimate: a spurious velocity
    pred = rest + 0.9 * slow + fast  # a prediction from rest of the same start (10 % too soft)
    assert np.all(marker_velocity(rec, reference=pred) == 0.0)
    v = 0.05
    moving = Recording(times=t, marker_rest=rest, markers=X + (v * t)[:, None, None] * u1)
    est = marker_velocity(moving, reference=pred)
    np.testing.assert_allclose(est, v * u1, atol=0.2 * v * np.abs(u1).max())


def test_auto_start_moves_only_the_recording_caught_mid_swing(tmp_path):
    """estimate_velocity="auto" (what diagnose uses): the release recorded from its held pose
    starts at rest (its prediction is unchanged), the recording cut mid-swing starts
    with the velocity its markers show beyond the prediction from rest."""
    bar = meshes.bar(L, W, W, (5, 2, 2))
    mat, dmp = Material("corotated", E0, 0.4, 1000.0), Damping(0, 0.002)
    tip = [[0.75 * L, -1, -1], [1, 1, 1]]
    load = {"box": tip, "force": [0, -0.25, 0.1]}
    scene = make_case(tmp_path, "cut", bar, mat, dmp, bar, mat, dmp, [[-1, -1, -1], [1e-6, 1, 1]],
                      [Motion("release", "train", 0.08, load=load), Motion("release", "train", 0.08, load=load)],
                      marker_fraction=0.5, noise=2e-5, seed=0)
    path = scene.parent / "train_1.npz"
    rec = load_recording(path)
    speed = np.linalg.norm(np.diff(rec.markers, axis=0), axis=2).mean(axis=1)
    k = int(np.argmax(speed[:40]))  # the fastest frame of the first swing
    save_recording(Recording(times=rec.times[k:], marker_rest=rec.marker_rest, markers=rec.markers[k:]), path)
    auto, rest = Problem(scene, estimate_velocity="auto"), Problem(scene)
    assert auto.start_velocity(auto.train[0]) is None
    assert auto.start_velocity(auto.train[1]) is not None
    model = rest.scene.model()
    # (equal up to the linearised replay's conjugate-gradient tolerance: its factor is reused)
    np.testing.assert_allclose(auto.predict(model, auto.train[0]), rest.predict(model, rest.train[0]),
                               rtol=0, atol=1e-9)
    r_auto = auto.residual(model, [auto.train[1]])
    r_rest = rest.residual(model, [rest.train[1]])
    assert float(r_auto @ r_auto) < 0.1 * float(r_rest @ r_rest)


def test_start_decision_survives_a_failing_held_pose(tmp_path, monkeypatch):
    """The moving start's pose is held at the best scale; where that static solve fails the
    nominal stiffness is tried, and where both fail the recording starts at rest: the start
    decision never stops a diagnosis (independent seed 12: Newton failed at a 0.3x scale)."""
    from matlearn.diagnosis import problem as prob

    bar = meshes.bar(L, W, W, (5, 2, 2))
    mat, dmp = Material("corotated", E0, 0.4, 1000.0), Damping(0, 0.002)
    tip = [[0.75 * L, -1, -1], [1, 1, 1]]
    load = {"box": tip, "force": [0, -0.25, 0.1]}
    scene = make_case(tmp_path, "cut", bar, mat, dmp, bar, mat, dmp, [[-1, -1, -1], [1e-6, 1, 1]],
                      [Motion("release", "train", 0.08, load=load)], marker_fraction=0.5, noise=2e-5, seed=0)
    path = scene.parent / "train_0.npz"
    rec = load_recording(path)
    speed = np.linalg.norm(np.diff(rec.markers, axis=0), axis=2).mean(axis=1)
    k = int(np.argmax(speed[:40]))
    save_recording(Recording(times=rec.times[k:], marker_rest=rec.marker_rest, markers=rec.markers[k:]), path)
    real = prob.initial_velocity
    calls = []

    def failing_once(scene_, model, *a, **kw):
        calls.append(float(np.median(model.mu)))
        if len(calls) == 1:
            raise RuntimeError("static_solve: Newton did not converge at load step 1")
        return real(scene_, model, *a, **kw)

    monkeypatch.setattr(prob, "initial_velocity", failing_once)
    auto = Problem(scene, estimate_velocity="auto")
    assert auto.start_velocity(auto.train[0]) is not None  # the nominal stiffness held it
    info = auto.start_info(auto.train[0])
    assert info["moving"] and len(info["velocity_failures"]) == 1

    def always(*a, **kw):
        raise RuntimeError("static_solve: Newton did not converge")

    monkeypatch.setattr(prob, "initial_velocity", always)
    auto = Problem(scene, estimate_velocity="auto")
    assert auto.start_velocity(auto.train[0]) is None
    assert not auto.start_info(auto.train[0])["moving"]


def test_the_velocity_window_spans_a_quarter_period_whatever_the_rate():
    """velocity_frames: a fixed 7 frames at 500 Hz span 12 ms, 1/9 of a 9 Hz period, where the
    cubic's slope is so uncertain that a start at 0.45 m/s (0.4 mm marker noise) passes the noise
    test as rest in 17 of 30 draws; the quarter-period window (14 frames) finds it in 28, with the
    right velocity. At 120 Hz the window stays 7 frames; without a model frequency the
    recording's own spectrum gives the period."""
    from matlearn.diagnosis.problem import velocity_frames

    K, rate, f, sigma, v = 20, 500.0, 9.0, 4e-4, 0.45
    w = 2 * np.pi * f
    t = np.arange(0.0, 0.2, 1.0 / rate)
    found = {7: 0, "window": 0}
    along = []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        rest = rng.standard_normal((K, 3)) * 0.05
        u = rng.standard_normal((K, 3))
        u /= np.linalg.norm(u)
        X = rest + (v / w) * np.sin(w * t)[:, None, None] * u + rng.normal(0, sigma, (len(t), K, 3))
        rec = Recording(times=t + 0.7, marker_rest=rest, markers=X)
        n = velocity_frames(rec, w)
        assert n == 14  # 0, 2, ..., 26 ms: a quarter of 111 ms
        assert abs(velocity_frames(rec, None) - n) <= 2  # the spectrum's peak (0.2 s resolves it coarsely)
        found[7] += bool(np.any(marker_velocity(rec, 7)))
        est = marker_velocity(rec, n)
        if np.any(est):
            found["window"] += 1
            along.append(float(np.sum(est * u)) / v)
    assert found[7] <= 15 and found["window"] >= 27, found
    assert 0.85 < np.median(along) < 1.25, np.median(along)
    slow = Recording(times=np.arange(30) / 120.0, marker_rest=rest, markers=rest + np.zeros((30, K, 3)))
    assert velocity_frames(slow, w) == 7
    assert velocity_frames(Recording(times=t[:12], marker_rest=rest, markers=X[:12]), w) == 7  # half at most


def test_a_start_must_also_fit_the_frames_after_its_window(tmp_path, monkeypatch):
    """start_in_motion's out-of-window check. The nominal model is the truth; the markers follow a
    start with velocity v* over the velocity window and fall back towards the start from rest
    after it (30 % of v*'s deviation left). The start with v* then removes over half the rest
    start's residual above the noise over the whole recording (the old rule: moving), but fits the
    frames after the window worse than the start at rest: at rest. Markers that keep following v*
    after the window: moving."""
    from matlearn import replay
    from matlearn.diagnosis import problem as prob
    from matlearn.diagnosis.problem import start_in_motion, velocity_frames

    bar = meshes.bar(L, W, W, (5, 2, 2))
    mat, dmp = Material("corotated", E0, 0.4, 1000.0), Damping(0, 0.002)
    tip = [[0.75 * L, -1, -1], [1, 1, 1]]
    scene = make_case(tmp_path, "glitch", bar, mat, dmp, bar, mat, dmp, [[-1, -1, -1], [1e-6, 1, 1]],
                      [Motion("release", "train", 0.04, load={"box": tip, "force": [0, -0.25, 0.1]})],
                      marker_fraction=0.5, noise=2e-5, seed=0)
    path = scene.parent / "train_0.npz"
    P = Problem(scene)
    rec = P.train[0]
    n = velocity_frames(rec, P.nominal_omega())
    model = P.scene.model()
    x0 = replay.initial_state(P.scene, model, rec, P.embedding(rec))[0]
    vstar = np.zeros_like(x0)
    vstar[:, 1] = 0.05 * (np.asarray(P.scene.mesh.vertices)[:, 0] / L) ** 2  # a bending swing, m/s
    rest = P.simulate_markers(model, rec, (x0, 0 * x0), P.fast_newton)[0]
    moved = P.simulate_markers(model, rec, (x0, vstar), P.fast_newton)[0]
    noise = np.random.default_rng(0).normal(0, 2e-5, rest.shape)
    monkeypatch.setattr(prob, "initial_velocity", lambda *a, **k: vstar)  # the mapped start is v*
    info = {}
    for after in (0.3, 1.0):
        share = np.full(rec.num_frames, after)
        share[:n] = 1.0
        save_recording(Recording(times=rec.times, marker_rest=rec.marker_rest,
                                 markers=rest + share[:, None, None] * (moved - rest) + noise), path)
        P = Problem(scene)
        info[after] = start_in_motion(P, P.train[0])[1]
    i = info[0.3]
    assert i["rss_rest"] - i["rss_moving"] >= 0.5 * (i["rss_rest"] - i["rss_noise"])  # passes the old rule
    assert i["rss_moving_after"] > i["rss_rest_after"] and not i["moving"]
    assert info[1.0]["moving"] and info[1.0]["rss_moving_after"] < info[1.0]["rss_rest_after"]
