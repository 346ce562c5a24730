"""Replay: initial state, simulation over a recording, predicted markers, the error metric."""
import numpy as np
import pytest

from matlearn import meshes, replay
from matlearn.materials import Damping, Material
from matlearn.recording import Recording
from matlearn.scene import Scene, vertices_in_box

H = 1e-3
TIP = [[0.199, -1, -1], [1, 1, 1]]


@pytest.fixture(scope="module")
def setup():
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(6, 1, 1))  # every vertex is on the surface
    box = [[-1, -1, -1], [1e-3, 1, 1]]
    scene = Scene(mesh, Material(youngs_modulus=2e5), Damping(alpha_stiffness=0.005),
                  vertices_in_box(mesh.vertices, box), H, fixed_box=box)
    model = scene.model()
    integ = scene.integrator(model)
    n = mesh.num_vertices
    f = np.zeros((n, 3))
    tip = vertices_in_box(mesh.vertices, TIP)
    f[tip, 1] = 0.5 / len(tip)
    integ.static_solve(f, load_steps=3)
    X, V = integ.simulate(60, np.zeros((n, 3)), 1)
    return scene, model, X, V, H * np.arange(61)


def test_trajectory_error_by_hand():
    obs = np.array([[[0, 0, 0], [1, 0, 0]], [[np.nan] * 3, [1, 1, 0]]], float)
    pred = np.array([[[0, 0, 0.3], [1, 0.4, 0]], [[7, 7, 7], [1, 1, 0]]], float)  # unseen: ignored
    err = replay.trajectory_error(pred, obs, object_size=10.0)
    assert err["max_error_pct"] == pytest.approx(4.0)
    assert err["rms_error_pct"] == pytest.approx(100 * np.sqrt((0.09 + 0.16 + 0) / 3) / 10)
    assert err["samples"] == 3
    pooled = replay.combine_errors([err, {"max_error_pct": 1.0, "rms_error_pct": 2.0, "samples": 1}])
    assert pooled["max_error_pct"] == pytest.approx(4.0)
    assert pooled["rms_error_pct"] == pytest.approx(np.sqrt((3 * err["rms_error_pct"] ** 2 + 4.0) / 4))
    with pytest.raises(ValueError, match="expected shape"):
        replay.trajectory_error(pred[:1], obs, 10.0)
    with pytest.raises(ValueError, match="no seen marker"):
        replay.trajectory_error(pred, np.full_like(obs, np.nan), 10.0)


def test_interpolate_frames_is_linear_and_held_outside():
    t = np.array([0.0, 0.1, 0.3])
    vals = np.stack([t * 2 + 1, -t], axis=1)  # (3, 2), linear in t
    at = np.array([0.05, 0.2, 0.3, -1.0, 5.0])
    out = replay.interpolate_frames(t, vals, at)
    np.testing.assert_allclose(out[:3], np.stack([at[:3] * 2 + 1, -at[:3]], 1), atol=1e-15)
    np.testing.assert_allclose(out[3], vals[0])
    np.testing.assert_allclose(out[4], vals[-1])


def test_replaying_the_truth_on_the_same_mesh_has_no_error(setup):
    scene, model, X, V, t = setup
    # Irregular sample times, not multiples of the time step.
    rng = np.random.default_rng(0)
    times = np.sort(np.concatenate([[0.0, t[-1]], rng.uniform(0, t[-1], 25)]))
    markers = replay.interpolate_frames(t, X, times)
    rec = Recording(times, scene.mesh.vertices, markers, at_rest_initially=False)
    x0, v0 = replay.initial_state(scene, model, rec)
    np.testing.assert_allclose(x0, X[0], atol=1e-9 * scene.object_size)
    assert np.all(v0 == 0)
    pred = replay.predict_markers(scene, model, rec)
    err = replay.trajectory_error(pred, rec, scene.object_size)
    assert err["max_error_pct"] < 1e-6
    # A different model disagrees: the metric is not blind.
    soft = scene.model(material=Material(youngs_modulus=1e5))
    assert replay.trajectory_error(replay.predict_markers(scene, soft, rec), rec, scene.object_size)[
        "max_error_pct"] > 0.5


def _sparse_recording(scene, X, t, seed=3):
    """12 markers at random points of random surface triangles, following the trajectory X."""
    rng = np.random.default_rng(seed)
    faces = scene.mesh.surface_faces[rng.choice(len(scene.mesh.surface_faces), 12, replace=False)]
    w = rng.dirichlet(np.ones(3), size=len(faces))
    rest = np.einsum("kj,kjd->kd", w, scene.mesh.vertices[faces])
    return Recording(t, rest, np.einsum("kj,tkjd->tkd", w, X[:, faces]))


def test_sparse_off_vertex_markers_give_a_close_initial_state(setup):
    scene, model, X, V, t = setup
    rec = _sparse_recording(scene, X, t)
    tip_disp = np.abs(X[0] - scene.mesh.vertices).max()
    x0, _ = replay.initial_state(scene, model, rec)
    assert np.abs(x0 - X[0]).max() < 0.06 * tip_disp
    # Refinement matters: nearest vertices alone are clearly worse.
    x0_plain, _ = replay.initial_state(scene, model, rec, refine=0)
    assert np.abs(x0_plain - X[0]).max() > 1.5 * np.abs(x0 - X[0]).max()
    err = replay.trajectory_error(replay.predict_markers(scene, model, rec), rec, scene.object_size)
    assert err["max_error_pct"] < 15 * tip_disp / scene.object_size  # < 15 % of the motion


def test_estimated_velocity_matches_backward_euler(setup):
    scene, model, X, V, t = setup
    rec = Recording(t[20:] - t[20], scene.mesh.vertices, X[20:])
    x0, v0 = replay.initial_state(scene, model, rec, velocity="estimate")
    np.testing.assert_allclose(x0, X[20], atol=1e-9)
    np.testing.assert_allclose(v0, V[21], atol=1e-6 * np.abs(V[21]).max())  # x21 = x20 + h v21
    with pytest.raises(ValueError, match="velocity"):
        replay.initial_state(scene, model, rec, velocity="guess")


def test_drive_points_are_followed(setup):
    scene, model, _, _, t = setup
    mesh, n = scene.mesh, scene.mesh.num_vertices
    tip = vertices_in_box(mesh.vertices, TIP)
    disp = 0.01 * np.sin(2 * np.pi * 10 * t)[:, None] * np.array([0.0, 1.0, 0.5])
    targets = mesh.vertices[tip][None] + disp[:, None]
    integ = scene.integrator(model)
    integ.set_prescribed(tip)
    X, _ = integ.simulate_constrained(targets[1:], np.zeros((n, 3)))
    rec = Recording(t, mesh.vertices, X, at_rest_initially=True, drive_rest=mesh.vertices[tip],
                    drive=targets)
    idx, tr = replay.drive_vertices(scene, rec)
    np.testing.assert_array_equal(idx, np.sort(tip))
    err = replay.trajectory_error(replay.predict_markers(scene, model, rec), rec, scene.object_size)
    assert err["max_error_pct"] < 1e-6


class _Flaky:
    """An integrator whose static_solve raises (as a Newton failure does) at the given calls."""

    def __init__(self, integ, fail_at):
        self._integ, self._fail_at, self.calls = integ, set(fail_at), 0

    def static_solve(self, *args, **kwargs):
        self.calls += 1
        if self.calls in self._fail_at:
            raise RuntimeError("static_solve: Newton did not converge at load step 1 (test)")
        return self._integ.static_solve(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._integ, name)


def test_held_pose_survives_failing_newton_solves(setup):
    from matlearn.embedding import embed_points

    scene, model, X, V, t = setup
    rec = _sparse_recording(scene, X, t)
    emb = embed_points(scene.mesh, rec.marker_rest)
    good = replay._held_pose(scene, model, rec, 0, emb, refine=3)
    one_pass = replay._held_pose(scene, model, rec, 0, emb, refine=1)
    # an increment fails: the increments are made finer and the pose is the same equilibrium
    flaky = _Flaky(scene.integrator(model), {1})
    x = replay._held_pose(scene, model, rec, 0, emb, integ=flaky, refine=3)
    np.testing.assert_allclose(x, good, atol=1e-6 * scene.object_size)
    assert flaky.calls > 4
    # a refinement pass fails (the increments took one solve here): the pose of the passes before
    incs = _Flaky(scene.integrator(model), set())
    replay._held_pose(scene, model, rec, 0, emb, integ=incs, refine=0)
    flaky = _Flaky(scene.integrator(model), {incs.calls + 2})
    x = replay._held_pose(scene, model, rec, 0, emb, integ=flaky, refine=3)
    np.testing.assert_allclose(x, one_pass, atol=1e-12)
    assert np.abs(one_pass - good).max() > 1e-6 * scene.object_size  # the passes matter
    # every retry fails: the failure is raised, not hidden
    with pytest.raises(RuntimeError, match="Newton"):
        replay._held_pose(scene, model, rec, 0, emb, integ=_Flaky(scene.integrator(model), range(1, 1000)))


def test_unconverged_newton_steps_warn():
    """A fast swing at a 5 ms step: with 2 Newton iterations half the steps stop at the limit
    without meeting the tolerance, and simulate_recording says how many (NonConvergenceWarning);
    with the default 8 iterations none does and nothing is said."""
    import warnings

    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(6, 1, 1))
    box = [[-1, -1, -1], [1e-3, 1, 1]]
    scene = Scene(mesh, Material(youngs_modulus=2e5), Damping(alpha_stiffness=0.005),
                  vertices_in_box(mesh.vertices, box), 5e-3, fixed_box=box)
    model = scene.model()
    V0 = np.asarray(mesh.vertices)
    rec = Recording(np.linspace(0, 0.06, 61), V0, np.repeat(V0[None], 61, 0), at_rest_initially=True)
    v = np.zeros_like(V0)
    v[:, 1] = 4.0 * V0[:, 0] / 0.2  # m/s, growing towards the tip
    with pytest.warns(replay.NonConvergenceWarning, match=r"of 12 implicit steps") as rec_w:
        replay.simulate_recording(scene, model, rec, state=(V0, v), max_newton=2)
    n = int(str(rec_w[0].message).split(": ")[1].split(" of ")[0])
    assert 0 < n <= 12
    with warnings.catch_warnings():
        warnings.simplefilter("error", replay.NonConvergenceWarning)
        replay.simulate_recording(scene, model, rec, state=(V0, v), max_newton=8)


def test_float32_times_end_on_the_step_they_mean(setup):
    """Times stored as float32 end a hair past a whole number of steps (0.3 s reads as
    0.30000001 s); the replay covers 0.3 s, not one step more, and the last frame is the
    simulation's last step. A span a real fraction of a step past it gets the extra step."""
    scene = setup[0]
    K = 2
    rest = np.zeros((K, 3))
    for span, rate, want in ((0.3, 100.0, 300), (0.3, 240.0, 300), (0.2995, 200.0, 300)):
        T = int(round(span * rate)) + 1
        t32 = np.linspace(0.0, span, T).astype(np.float32)
        rec = Recording(t32, marker_rest=rest, markers=np.zeros((T, K, 3)))
        assert rec.times[-1] > span or span == 0.2995  # the float32 rounding this is about
        sim_t = replay.simulation_times(scene, rec)
        assert len(sim_t) - 1 == want, (span, rate)
        assert sim_t[-1] >= rec.times[-1] - replay.STEP_ROUNDING * H
    assert replay.steps_covering(0.3 + 0.01 * H, H) == 301
    assert replay.steps_covering(0.3 + 1e-4 * H, H) == 300
