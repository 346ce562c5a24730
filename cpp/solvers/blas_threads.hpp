#pragma once
/// Threads of the BLAS under CHOLMOD's supernodal factorisation (OpenBLAS on Debian's
/// libopenblas0-pthread). OpenBLAS threads busy-wait between calls and then starve matlearn's
/// OpenMP element loops: on 2 cores, a 10k-tet backward-Euler step takes 95 ms with 2 OpenMP +
/// 2 OpenBLAS threads (the default of both libraries) and 53 ms with OpenBLAS on one thread
/// (81 ms on one thread of each). The Python module sets one OpenBLAS thread when it is loaded,
/// unless OPENBLAS_NUM_THREADS (or GOTO_NUM_THREADS) says otherwise.

namespace matlearn::solvers {

/// OpenBLAS's thread count, or -1 when the loaded BLAS is not OpenBLAS (no such control).
int blas_threads();

/// Set OpenBLAS's thread count (n >= 1); false when the loaded BLAS is not OpenBLAS.
bool set_blas_threads(int n);

}  // namespace matlearn::solvers
