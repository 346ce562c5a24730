"""Independent simulations on the machine's cores.

The C++ calls release the GIL, so simulations of different models or recordings run in
parallel on Python threads. Two helpers:

* :func:`threads`: how many threads to use: MATLEARN_THREADS if set (1 keeps everything on one
  thread, e.g. on a machine shared with other jobs; the results are the same), else the cores
  this process may run on, at most MAX_THREADS.
* :func:`pmap`: ``[fn(x) for x in items]`` on up to :func:`threads` threads, results in order.
  For tasks whose result depends on their input alone (a stateless integrator run, the
  learning's and the baseline's replays), so the result is bitwise the serial one whatever the
  cores. The diagnosis's linearised replays keep solver state between simulations and use
  ``diagnosis.problem.Problem.parallel`` (fixed slots) instead.

A task that raises stops the later tasks (in item order) not yet started, and the exception of
the *first* failing task in item order reaches the caller, as in the serial loop (later tasks
that already ran are discarded; a running one may poll :func:`cancelled` to stop early). A
Ctrl-C in the caller stops the tasks not yet started, waits for the running ones (one
simulation each) and is re-raised. Inside a task, pmap runs serially on that thread (no nested
pools, no oversubscription).
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

MAX_THREADS = 2  # this project's machines; more threads would only add memory

_local = threading.local()


def threads() -> int:
    """MATLEARN_THREADS if set (a whole number >= 1), else the cores this process may run on,
    at most MAX_THREADS."""
    env = os.environ.get("MATLEARN_THREADS", "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"MATLEARN_THREADS must be a whole number of threads, got {env!r}") from None
    else:
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(MAX_THREADS, n))


def inside_task() -> bool:
    """True while a pmap task runs on this thread (nested calls run serially there)."""
    return getattr(_local, "state", None) is not None


class Cancelled(Exception):
    """Raised by :func:`check_cancelled` in a task whose result can no longer be used."""


def cancelled() -> bool:
    """Inside a pmap task: whether its result can no longer be used (an earlier task in item
    order failed, or the caller stopped). A long task may poll it and give up early; outside a
    task always False."""
    state = getattr(_local, "state", None)
    if state is None:
        return False
    stop, failed, index = state
    return stop.is_set() or index > failed[0]


def check_cancelled() -> None:
    """Raise Cancelled inside a pmap task whose result can no longer be used (:func:`cancelled`),
    e.g. between the chunks of a bounded forward check (learning/loop.py)."""
    if cancelled():
        raise Cancelled("stopped: an earlier task failed or the run was interrupted")


def pmap(fn, items) -> list:
    """[fn(x) for x in items], on up to threads() threads (module docstring: order, failures,
    Ctrl-C, nesting). Usable as scipy's ``workers`` map."""
    items = list(items)
    if inside_task():
        return [fn(x) for x in items]
    stop = threading.Event()
    failed = [len(items)]  # the lowest index whose task raised; later tasks are not started
    lock = threading.Lock()

    def run(i):
        if stop.is_set() or i > failed[0]:
            return None
        _local.state = (stop, failed, i)
        try:
            return fn(items[i])
        except BaseException:
            with lock:
                failed[0] = min(failed[0], i)
            raise
        finally:
            _local.state = None

    n = min(threads(), len(items))
    if n < 2:  # in the caller's thread, each item a task all the same (nesting, cancellation)
        return [run(i) for i in range(len(items))]
    pool = ThreadPoolExecutor(n, thread_name_prefix="matlearn")
    try:
        jobs = [pool.submit(run, i) for i in range(len(items))]
        out = []
        for job in jobs:  # in order: the first failure in item order is the one raised
            out.append(job.result())
        return out
    except BaseException:  # a task's exception, or Ctrl-C in the caller's thread
        stop.set()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
