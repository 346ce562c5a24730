"""Parallel simulations in the diagnosis (Problem.parallel, Problem.prefetch): results in task
order, each task on its fixed runner slot, bit-identical whatever the number of cores, equal to
the serial simulations to the replay's solver tolerance, failures left to the caller."""
import threading
import time

import numpy as np
import pytest

from matlearn import parallel
from matlearn.diagnosis.effects import EffectContext, build_model
from matlearn.diagnosis.problem import SLOTS, Problem

from diagnosis_cases import tiny_case


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return tiny_case(tmp_path_factory.mktemp("par"), "par", E_scale=1.3, seed=5)


def _models(P, scales=(-0.3, -0.1, 0.0, 0.15, 0.3)):
    s = P.scene
    ctx = EffectContext(s.mesh, s.material, s.damping, s.fixed)
    return [build_model(ctx, {"stiffness_scale": [t]}) for t in scales]


def test_tasks_run_in_order_on_their_slots(scene):
    P = Problem(scene)
    seen = []
    lock = threading.Lock()

    def task(i):
        def run():
            with lock:
                seen.append((i, P._local.slot, threading.current_thread().name))
            return i * i
        return run

    out = P.parallel([task(i) for i in range(7)])
    assert out == [i * i for i in range(7)]
    assert sorted(i for i, _, _ in seen) == list(range(7))
    for i, slot, _ in seen:
        assert slot == i % SLOTS
    for slot in range(SLOTS):  # each slot's tasks in order, on one thread
        mine = [(i, name) for i, s, name in seen if s == slot]
        assert [i for i, _ in mine] == sorted(i for i, _ in mine)
        assert len({name for _, name in mine}) == 1
    assert getattr(P._local, "slot", 0) == 0  # the caller's own slot is untouched


def test_a_failing_task_stops_every_slot(scene):
    P = Problem(scene)
    ran, failed = [], threading.Event()

    def fail():
        failed.set()
        raise RuntimeError("step 3: linear solve produced NaN (diverged)")

    def slow():  # running beside the failure on the other slot
        failed.wait(5.0)
        time.sleep(0.2)
        ran.append(1)

    tasks = [fail, slow] + [lambda i=i: ran.append(i) for i in range(2, 8)]
    with pytest.raises(RuntimeError, match="diverged"):
        P.parallel(tasks)
    assert 2 not in ran and 3 not in ran  # neither slot went on after the failure
    assert P.parallel([lambda: 1, lambda: 2]) == [1, 2]  # and the problem is usable after it


@pytest.mark.parametrize("threads", ["1", "2"])  # one thread runs both slots in turn, the same way
def test_nested_tasks_run_on_the_outer_task_slot(scene, monkeypatch, threads):
    monkeypatch.setenv("MATLEARN_THREADS", threads)
    P = Problem(scene)

    def outer(i):
        return lambda: P.parallel([lambda: P._local.slot, lambda: P._local.slot])

    out = P.parallel([outer(i) for i in range(4)])
    assert out == [[i % SLOTS] * 2 for i in range(4)]


def test_prefetched_predictions_do_not_depend_on_the_cores(scene, monkeypatch):
    threaded = Problem(scene)
    models = _models(threaded)
    threaded.prefetch(models)
    assert threaded.simulations == len(models) * len(threaded.train)
    a = [threaded.predict(m, rec) for m in models for rec in threaded.train]
    assert threaded.simulations == len(models) * len(threaded.train)  # every call found its result

    monkeypatch.setenv("MATLEARN_THREADS", "1")  # the serial fallback
    assert parallel.threads() == 1
    single = Problem(scene)
    single.prefetch(_models(single))
    b = [single.predict(m, rec) for m in _models(single) for rec in single.train]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)

    # and the same as simulating one after the other on one runner, to the solver's tolerance
    serial = Problem(scene)
    c = [serial.predict(m, rec) for m in _models(serial) for rec in serial.train]
    for x, y in zip(a, c):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-9 * serial.object_size)
    # the models differ: a prefetch that returned one model's markers for all would fail here
    assert np.abs(a[0] - a[-1]).max() > 1e-4 * serial.object_size


def test_prefetch_takes_each_models_solver_and_runs_extra_tasks(scene):
    """The held-out stage prefetches full-Newton and fast predictions in one batch, with the
    refined mesh's gap as an extra task (pipeline._prefetch_gaps)."""
    P = Problem(scene)
    models = _models(P, (0.0, 0.2))
    assert P.prefetch(models, P.train, [False, True], extra=[lambda: "a", lambda: "b"]) == ["a", "b"]
    n = P.simulations
    assert n == 2 * len(P.train)
    P.predict(models[0], P.train[0], fast=False)
    P.predict(models[1], P.train[0], fast=True)
    assert P.simulations == n  # each memoised with its own solver
    P.predict(models[0], P.train[0], fast=True)
    assert P.simulations == n + 1  # not with the other one


def test_the_thread_count_can_be_set_and_a_bad_one_is_named(monkeypatch):
    monkeypatch.setenv("MATLEARN_THREADS", "8")
    assert parallel.threads() == parallel.MAX_THREADS == SLOTS  # never more threads than runner slots
    monkeypatch.setenv("MATLEARN_THREADS", "0")
    assert parallel.threads() == 1
    monkeypatch.setenv("MATLEARN_THREADS", "two")
    with pytest.raises(ValueError, match="MATLEARN_THREADS"):
        parallel.threads()


def test_a_failed_prefetch_is_met_by_the_callers_own_call(scene, monkeypatch):
    P = Problem(scene)
    models = _models(P, (0.0, 0.2))
    bad = P.fingerprint(models[1])
    real = P.simulate_markers

    def failing(model, rec, state, newton):
        if P.fingerprint(model) == bad:
            raise RuntimeError("step 3: linear solve produced NaN (diverged)")
        return real(model, rec, state, newton)

    monkeypatch.setattr(P, "simulate_markers", failing)
    P.prefetch(models)  # does not raise
    P.predict(models[0], P.train[0])
    with pytest.raises(RuntimeError, match="diverged"):
        P.predict(models[1], P.train[0])


def test_pmap_inside_a_problem_task_runs_on_the_tasks_own_thread(scene, monkeypatch):
    """The learning's pmap called from a diagnosis task does not start a pool of its own."""
    monkeypatch.setenv("MATLEARN_THREADS", "2")
    P = Problem(scene)

    def task():
        me = threading.current_thread().name
        return parallel.pmap(lambda x: threading.current_thread().name, range(3)) == [me] * 3 != [
            threading.main_thread().name] * 3

    assert P.parallel([task] * 4) == [True] * 4
    assert not parallel.inside_task()  # the mark is the task's only
