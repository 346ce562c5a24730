"""POD (proper orthogonal decomposition) basis for the reduced space-time step (method.md 5).

The basis spans the displacements of a forward simulation (and optionally of other trajectories,
e.g. the marker-following initial trajectory): x = x_base + Phi z. Rows of clamped and driven
vertices are zero, so those vertices always follow x_base.
"""
from __future__ import annotations

import numpy as np

# Snapshot matrices with at least this many entries get their leading singular vectors from a
# seeded randomized range finder (below: the full SVD). A 6k-tet bar with three 1001-frame
# trajectories (4263 x 3003) took 12-20 s for the full SVD and ~1 s this way.
RANDOMIZED_MIN_ENTRIES = 4_000_000


def leading_singular(A: np.ndarray, k: int, oversample: int = 40, power: int = 3,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(U (m, k), s (k,)): the k leading left singular vectors and values of A (m, n), by a
    randomized range finder (Halko, Martinsson & Tropp 2011, algorithm 4.4: Gaussian test matrix
    with `oversample` extra columns, `power` orthonormalised power iterations) and the exact SVD
    of the projected (k + oversample) x n matrix. Deterministic for a seed. The subspace error is
    of order (s_{k+oversample+1} / s_k)^(2 power + 1): round-off for the fast-decaying spectra
    of smooth trajectories (tests/python/test_learn_scale.py compares it with the full SVD)."""
    m, n = A.shape
    ell = min(k + oversample, m, n)
    Q, _ = np.linalg.qr(A @ np.random.default_rng(seed).standard_normal((n, ell)))
    for _ in range(power):
        Q, _ = np.linalg.qr(A.T @ Q)
        Q, _ = np.linalg.qr(A @ Q)
    Ub, s, _ = np.linalg.svd(Q.T @ A, full_matrices=False)
    k = min(k, ell)
    return Q @ Ub[:, :k], s[:k]


def pod_basis(trajectories, base, constrained, modes: int, window: float = 1.0,
              stride: int = 1) -> np.ndarray:
    """Orthonormal basis Phi (3n, r) of the dominant displacement directions.

    trajectories: list of position arrays (frames, n, 3); base: (n, 3) or matching (frames, n, 3)
    per trajectory (list); constrained: vertex indices whose rows are zeroed; modes: r;
    window: fraction of each trajectory's frames used (its first part, where motion is largest);
    stride: keep every stride-th frame. Modes with negligible singular values are dropped, so the
    returned r may be smaller than `modes`.
    """
    if modes < 1:
        raise ValueError(f"modes must be >= 1, got {modes}")
    if not 0 < window <= 1:
        raise ValueError(f"window must be in (0, 1], got {window}")
    cols = []
    bases = base if isinstance(base, (list, tuple)) else [base] * len(trajectories)
    for X, b in zip(trajectories, bases):
        X = np.asarray(X, float)
        if X.ndim != 3 or X.shape[2] != 3:
            raise ValueError(f"trajectory: expected shape (frames, n, 3), got {X.shape}")
        nf = max(2, int(round(window * len(X))))
        D = X[:nf:stride] - np.asarray(b, float)[: nf : stride] if np.ndim(b) == 3 else X[:nf:stride] - b
        D = D.copy()
        D[:, constrained] = 0.0
        cols.append(D.reshape(len(D), -1))
    A = np.concatenate(cols, axis=0).T  # (3n, samples)
    if not np.any(A):
        raise ValueError("pod_basis: the trajectories do not move (all displacements are zero)")
    if A.size >= RANDOMIZED_MIN_ENTRIES and modes + 40 < min(A.shape):
        U, s = leading_singular(A, modes)
        U[~A.any(axis=1)] = 0.0  # constrained rows exactly zero (the space-time tests for it)
    else:
        U, s, _ = np.linalg.svd(A, full_matrices=False)
    keep = int(min(modes, np.sum(s > 1e-10 * s[0])))
    return np.ascontiguousarray(U[:, :keep])
