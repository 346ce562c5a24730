"""matlearn.parallel: independent simulations on the cores give the serial results bitwise
(order, failures, nesting), and the learning paths that use it (the baseline fit's
finite-difference columns, the loop's bounded forward checks, replay.score) do not depend on
the thread count."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from matlearn import meshes, parallel
from matlearn.embedding import embed_points
from matlearn.learning import loop
from matlearn.learning.baseline import fit_parameters
from matlearn.materials import Damping, Material
from matlearn.replay import score
from matlearn.scene import load_scene
from matlearn.synthetic import Motion, make_case


@pytest.fixture(autouse=True)
def two_threads(monkeypatch):
    monkeypatch.setenv("MATLEARN_THREADS", "2")


def test_pmap_keeps_the_order_and_runs_on_two_threads():
    names = set()
    barrier = threading.Barrier(2, timeout=10)

    def task(x):
        names.add(threading.current_thread().name)
        if x < 2:
            barrier.wait()  # both first tasks at once: fails (BrokenBarrierError) on one thread
        return x * x

    assert parallel.pmap(task, range(7)) == [x * x for x in range(7)]
    assert len(names) == 2 and threading.current_thread().name not in names


def test_pmap_raises_the_first_failure_in_item_order_and_skips_later_tasks():
    started = []

    def task(x):
        started.append(x)
        if x == 1:
            time.sleep(0.3)  # fails after task 2 has failed
            raise ValueError("one")
        if x == 2:
            raise KeyError("two")
        return x

    with pytest.raises(ValueError, match="one"):  # the serial loop's exception, not the earlier-timed one
        parallel.pmap(task, range(40))
    assert 0 in started and 1 in started and len(started) < 40  # later tasks were not started


def test_a_running_task_sees_that_an_earlier_one_failed():
    seen = {}

    def task(x):
        if x == 0:
            time.sleep(0.1)
            raise RuntimeError("first")
        for _ in range(200):  # task 1 polls until task 0 has failed
            if parallel.cancelled():
                seen[x] = True
                return None
            time.sleep(0.01)
        return x

    with pytest.raises(RuntimeError, match="first"):
        parallel.pmap(task, range(2))
    assert seen == {1: True}
    assert not parallel.cancelled()  # outside a task


def test_nested_pmap_runs_serially_on_the_task_thread():
    def inner(x):
        return threading.current_thread().name

    def outer(x):
        names = parallel.pmap(inner, range(3))
        return len(set(names)) == 1 and names[0] == threading.current_thread().name

    assert all(parallel.pmap(outer, range(4)))


def test_one_thread_runs_in_the_callers_thread(monkeypatch):
    monkeypatch.setenv("MATLEARN_THREADS", "1")
    me = threading.current_thread().name
    assert parallel.pmap(lambda x: threading.current_thread().name, range(3)) == [me] * 3
    monkeypatch.setenv("MATLEARN_THREADS", "x")
    with pytest.raises(ValueError, match="MATLEARN_THREADS"):
        parallel.pmap(lambda x: x, range(3))


@pytest.fixture(scope="module")
def two_recordings(tmp_path_factory):
    """A bar released from two tip loads (train) and a third (test); nominal 40 % too stiff."""
    L = 0.08
    mesh = meshes.bar(L, 0.02, 0.02, cells=(5, 1, 1))
    tip = [[L - 0.011, -1, -1], [1, 1, 1]]
    motions = [Motion("release", "train", 0.06, load={"box": tip, "force": [0, 0.25, 0.08]}),
               Motion("release", "train", 0.08, load={"box": tip, "force": [0.1, -0.35, 0.15]}),
               Motion("release", "test", 0.06, load={"box": tip, "force": [0, 0.3, -0.05]})]
    path = make_case(tmp_path_factory.mktemp("par"), "bar", mesh,
                     Material("neo_hookean", 2e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     mesh, Material("corotated", 2.8e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     [[-1, -1, -1], [1e-4, 1, 1]], motions, marker_fraction=0.5, seed=3)
    return load_scene(path)


def _both(monkeypatch, fn):
    """fn() with two threads and with one."""
    monkeypatch.setenv("MATLEARN_THREADS", "2")
    a = fn()
    monkeypatch.setenv("MATLEARN_THREADS", "1")
    return a, fn()


def test_the_baseline_fit_does_not_depend_on_the_threads(two_recordings, monkeypatch):
    a, b = _both(monkeypatch, lambda: fit_parameters(two_recordings, max_evaluations=8))
    assert a["evaluations"] == b["evaluations"] >= 8
    assert a["train_rms_pct"] == b["train_rms_pct"]
    assert a["material"].youngs_modulus == b["material"].youngs_modulus
    assert a["material"].poisson_ratio == b["material"].poisson_ratio
    assert a["damping"] == b["damping"]
    # it fitted something: the 40 % too stiff nominal moved towards the truth
    assert float(a["material"].youngs_modulus) < 2.6e5


def test_score_does_not_depend_on_the_threads(two_recordings, monkeypatch):
    a, b = _both(monkeypatch, lambda: score(two_recordings, two_recordings.model(), "train"))
    assert len(a["recordings"]) == 2 and a == b
    assert a["recordings"][0]["max_error_pct"] != a["recordings"][1]["max_error_pct"]


def test_a_bounded_forward_check_stops_as_the_serial_one(two_recordings, monkeypatch):
    sc = two_recordings
    recs = sc.recordings_with_role("train")
    embs = [embed_points(sc.mesh, r.marker_rest) for r in recs]
    model = sc.model()
    errs, _ = loop._errors(sc, model, recs, embs)
    whole = [float(e.max()) for e in errs]
    assert whole[1] > whole[0]  # the case tests a stop in the second recording (below)
    total = sum(len(loop.simulation_times(sc, r)) - 1 for r in recs)
    # both recordings exceed the first bound; only the second exceeds the other, after the first whole
    for bound in (0.5 * whole[0], 0.5 * (whole[0] + whole[1])):
        def check():
            with pytest.raises(loop.ErrorBoundExceeded) as info:
                loop._errors(sc, model, recs, embs, bound=bound)
            return info.value.lower_bound, info.value.simulated
        a, b = _both(monkeypatch, check)
        assert a == b and a[0] > bound
        if bound > whole[0]:  # the first recording was simulated whole before the second stopped
            first = (len(loop.simulation_times(sc, recs[0])) - 1) / total
            assert first < a[1] < 1.0
    # a bound both recordings stay under: the same errors as without a bound, either way
    a, b = _both(monkeypatch, lambda: loop._errors(sc, model, recs, embs, bound=1.01 * max(whole))[0])
    for x, y, z in zip(a, b, errs):
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(x, z)


def test_the_released_start_does_not_depend_on_the_threads(two_recordings, monkeypatch):
    from matlearn.replay import initial_state

    sc = two_recordings
    rec = sc.recordings_with_role("train")[1]
    emb = embed_points(sc.mesh, rec.marker_rest)
    a, b = _both(monkeypatch, lambda: initial_state(sc, sc.model(), rec, emb, start="released")[0])
    np.testing.assert_array_equal(a, b)
    held = initial_state(sc, sc.model(), rec, emb)[0]  # its candidates and refinement moved the pose
    assert np.abs(a - held).max() > 1e-6 * sc.object_size


def _timeless(x):
    """x without its wall-clock entries (keys with "wall")."""
    if isinstance(x, dict):
        return {k: _timeless(v) for k, v in x.items() if "wall" not in k}
    if isinstance(x, list):
        return [_timeless(v) for v in x]
    return x


def test_a_learning_iteration_does_not_depend_on_the_threads(two_recordings, tmp_path, monkeypatch):
    """Two train recordings: their space-time problems, forward checks and scores run side by
    side; the learned correction and every metric are bitwise the one-thread run's."""
    from matlearn.learning import LearnOptions, learn

    opts = LearnOptions(iterations=2, modes=10, centers=8)
    runs = iter(("two", "one"))
    a, b = _both(monkeypatch, lambda: learn(two_recordings, tmp_path / next(runs), opts, log=None))
    assert _timeless(a["metrics"]) == _timeless(b["metrics"])
    st = a["metrics"][0]["spacetime"]
    assert len(st) == 2 and st[0]["cost"] != st[1]["cost"]  # both recordings, each its own problem
    assert a["final"]["train"]["max_error_pct"] < a["nominal"]["train"]["max_error_pct"]  # it learned
    for x, y in zip(a["params"].to_arrays().values(), b["params"].to_arrays().values()):
        np.testing.assert_array_equal(x, y)
