"""The loop's savings for long recordings (bench/learning_scale.py) keep its results:

* a bounded forward check simulates bitwise the trajectory of an unbounded one and stops, with a
  lower bound of the max error, once an error exceeds the bound;
* early-stopped candidate checks (LearnOptions.early_stop) give the same learning run: same
  decisions, same accepted corrections, same train errors;
* chord Gauss-Newton steps (jacobian_every > 1) reuse the Jacobian blocks (one CG iteration with
  the frozen preconditioner) and still recover a known trajectory.
"""
import numpy as np
import pytest

from matlearn import meshes
from matlearn.embedding import embed_points
from matlearn.learning import LearnOptions, learn
from matlearn.learning import loop as loop_mod
from matlearn.learning.spacetime import build_problem, solve_spacetime
from matlearn.materials import Damping, Material
from matlearn.recording import Recording
from matlearn.scene import Scene, load_scene

from learning_cases import scaled_fit, small_bar_case

OPTS = dict(modes=12, centers=12, ridges=(1e-6,))


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    return small_bar_case(tmp_path_factory.mktemp("scale"))


def test_bounded_check_is_the_full_simulation_or_stops_above_the_bound(case):
    sc = load_scene(case)
    recs = sc.recordings_with_role("train")
    embs = [embed_points(sc.mesh, r.marker_rest) for r in recs]
    model = sc.model()
    errs, sims = loop_mod._errors(sc, model, recs, embs)
    worst = max(e.max() for e in errs)
    b_errs, b_sims = loop_mod._errors(sc, model, recs, embs, bound=1.01 * worst)
    for a, b in zip(sims, b_sims):
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
    for a, b in zip(errs, b_errs):
        assert np.array_equal(a, b)
    with pytest.raises(loop_mod.ErrorBoundExceeded) as stop:
        loop_mod._errors(sc, model, recs, embs, bound=0.5 * worst)
    assert 0.5 * worst < stop.value.lower_bound <= worst
    assert 0 < stop.value.simulated < 1


def test_early_stopped_checks_give_the_same_run(case, tmp_path, monkeypatch):
    # 4x the fitted correction overshoots: the full step is worse, the shortened ones are
    # checked against the current error; two smoothing candidates, the second checked against
    # the first.
    monkeypatch.setattr(loop_mod, "solve_fit", scaled_fit(4.0))
    runs = {}
    for stop in (False, True):
        runs[stop] = learn(load_scene(case), tmp_path / f"run_{stop}",
                           LearnOptions(iterations=2, early_stop=stop, smoothing=(1e-3, 1.0), **OPTS),
                           log=None)
    full, fast = runs[False]["metrics"], runs[True]["metrics"]
    assert [m["train"] for m in full] == [m["train"] for m in fast]
    assert [m.get("update") for m in full] == [m.get("update") for m in fast]
    for a, b in zip(full, fast):
        if "fit" not in a:
            continue
        assert a["fit"]["update_step"] == b["fit"]["update_step"]
        for ta, tb in zip(a["fit"]["steps_tried"] + a["fit"]["ridge_candidates"],
                          b["fit"]["steps_tried"] + b["fit"]["ridge_candidates"]):
            if tb.get("stopped_early"):  # a lower bound, above what it had to beat
                assert tb["train_max_error_pct"] <= ta["train_max_error_pct"]
            else:
                assert tb["train_max_error_pct"] == ta["train_max_error_pct"]
    stopped = [t for m in fast if "fit" in m for t in m["fit"]["steps_tried"] + m["fit"]["ridge_candidates"]
               if t.get("stopped_early")]
    assert stopped, "the scenario must exercise an early stop"
    pa, pb = runs[False]["params"], runs[True]["params"]
    assert (pa is None) == (pb is None)
    if pa is not None:
        assert np.array_equal(pa.weights, pb.weights) and np.array_equal(pa.linear, pb.linear)


def test_chord_gauss_newton_reuses_the_jacobian_and_recovers_the_trajectory():
    mesh = meshes.bar(0.06, 0.02, 0.02, cells=(3, 1, 1))
    V = np.asarray(mesh.vertices)
    sc = Scene(mesh=mesh, material=Material("neo_hookean", 2e5, 0.4, 1000.0), damping=Damping(0.5, 0.002),
               fixed=np.flatnonzero(V[:, 0] < 1e-9), time_step=1e-3)
    model = sc.model()
    n = len(V)
    integ = sc.integrator(model, max_newton=30, tolerance=1e-12)
    integ.set_state(V, np.zeros((n, 3)))
    X, _ = integ.simulate(40, np.zeros((n, 3)), 1)
    rec = Recording(np.arange(41) * 1e-3, V.copy(), X.copy(), at_rest_initially=True)
    free = np.setdiff1d(np.arange(n), sc.fixed)
    dofs = (3 * free[:, None] + np.arange(3)).ravel()
    phi = np.zeros((3 * n, len(dofs)))
    phi[dofs, np.arange(len(dofs))] = 1.0
    start = np.repeat(V[None], len(X), axis=0)
    size = meshes.object_size(mesh)
    out = {}
    for k in (1, 3):
        setup = build_problem(sc, model, rec, phi, 1.0)
        out[k] = solve_spacetime(setup, start, iterations=10, tolerance=1e-6, jacobian_every=k, solver="pcgls")
        assert np.abs(out[k]["X"] - X).max() < 1e-6 * size, k
    # Chord steps solve with the exact preconditioner of the blocks they reuse (refactorised with
    # them): one CG iteration each; exact steps keep the first step's preconditioner and need more.
    assert all(c == 1 for c in out[3]["report"]["cg_iterations"]), out[3]["report"]["cg_iterations"]
    assert max(out[1]["report"]["cg_iterations"][1:]) > 1
    # Levenberg-Marquardt re-evaluates the Jacobian at every step: the core refuses chord steps,
    # and solve_spacetime's default turns to the line-search solver for them.
    Z0 = np.ascontiguousarray(setup.project(start))
    with pytest.raises(ValueError, match="jacobian_every"):
        setup.problem.solve(Z0, 3, 400, 1e-8, 1e-6, "lm", None, 3)
    with pytest.raises(ValueError, match="jacobian_every"):
        solve_spacetime(setup, start, iterations=10, tolerance=1e-6, jacobian_every=3, solver="lm")
    chord = solve_spacetime(setup, start, iterations=10, tolerance=1e-6, jacobian_every=3)
    assert chord["report"]["cg_iterations"] == out[3]["report"]["cg_iterations"]


def test_randomized_pod_spans_the_full_svd_basis(monkeypatch):
    """The POD basis of large snapshot matrices (randomized range finder) spans the same leading
    subspace as the full SVD, on smooth trajectories (fast-decaying spectrum) and random data."""
    from matlearn.learning import pod

    rng = np.random.default_rng(4)
    n, frames = 150, 301
    t = np.linspace(0, 1, frames)
    shapes = rng.standard_normal((8, n, 3))
    X = sum(np.exp(-k) * np.sin((k + 1) * 7 * t + k)[:, None, None] * shapes[k] for k in range(8))
    X = X + 1e-9 * rng.standard_normal(X.shape)  # a noise floor far below the leading modes
    base = np.zeros((n, 3))
    ref = pod.pod_basis([X, 0.5 * X[::-1]], base, [0, 1], 6)
    monkeypatch.setattr(pod, "RANDOMIZED_MIN_ENTRIES", 1)
    fast = pod.pod_basis([X, 0.5 * X[::-1]], base, [0, 1], 6)
    assert fast.shape == ref.shape
    assert np.allclose(fast.T @ fast, np.eye(6), atol=1e-12)
    assert np.linalg.norm(ref - fast @ (fast.T @ ref)) < 1e-8
    assert not fast[:6].any()  # constrained vertices 0, 1 have zero rows
    A = rng.standard_normal((200, 120)) @ np.diag(0.7 ** np.arange(120)) @ rng.standard_normal((120, 120))
    U, s = pod.leading_singular(A, 10)
    Ur, sr, _ = np.linalg.svd(A, full_matrices=False)
    assert np.allclose(s, sr[:10], rtol=1e-10)
    assert np.linalg.norm(Ur[:, :10] - U @ (U.T @ Ur[:, :10])) < 1e-8


def test_first_search_stops_checks_above_the_current_error_and_can_stop_at_a_rejection(case, tmp_path,
                                                                                       monkeypatch):
    # The negated correction: every candidate and every shortened step is worse than the current
    # (nominal) model. "first" checks each against the current error and stops it once above;
    # without retries the loop ends at the first rejected update.
    monkeypatch.setattr(loop_mod, "solve_fit", scaled_fit(-1.0))
    res = learn(load_scene(case), tmp_path / "run",
                LearnOptions(iterations=4, ridge_search="first", retry_rejected=False, smoothing=(1e-3, 1.0),
                             extrapolation=((0.0, 0.0),), **OPTS), log=None)  # one family: 2 candidates
    ms = res["metrics"]
    assert [m.get("update") for m in ms] == ["rejected"] and ms[-1]["stop"] == "no improving update"
    cur = ms[0]["train"]["max_error_pct"]
    checks = ms[0]["fit"]["ridge_candidates"] + ms[0]["fit"]["steps_tried"][1:]
    assert len(checks) == 2 + len(LearnOptions().backtrack)  # the 2 candidates, then every shortened step
    assert all(c["stopped_early"] and c["train_max_error_pct"] > cur for c in checks)
    assert res["params"] is None
