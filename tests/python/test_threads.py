"""Thread settings of the C++ core: OpenBLAS (under CHOLMOD) runs on one thread unless the user
set OPENBLAS_NUM_THREADS (its spinning threads starved the OpenMP element loops: a 10k-tet step
took 95 ms with both libraries' defaults on 2 cores, 53 ms with one OpenBLAS thread)."""
import os
import subprocess
import sys

import pytest

from matlearn import _core


def _blas_threads_in_child(env_extra: dict) -> int:
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS")}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", "from matlearn import _core; print(_core.blas_threads())"],
                         env=env, capture_output=True, text=True, check=True)
    return int(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(_core.blas_threads() < 0, reason="the BLAS under CHOLMOD is not OpenBLAS")
def test_openblas_runs_on_one_thread_unless_the_user_says_otherwise():
    assert _blas_threads_in_child({}) == 1
    assert _blas_threads_in_child({"OPENBLAS_NUM_THREADS": "2"}) == 2
    before = _core.blas_threads()
    try:
        assert _core.set_blas_threads(2) and _core.blas_threads() == 2
    finally:
        _core.set_blas_threads(before)
    with pytest.raises(ValueError, match="n must be >= 1"):
        _core.set_blas_threads(0)

