"""POD (proper orthogonal decomposition) basis for the reduced space-time step (method.md 5).

The basis spans the displacements of a forward simulation (and optionally of other trajectories,
e.g. the marker-following initial trajectory): x = x_base + Phi z. Rows of clamped and driven
vertices are zero, so those vertices always follow x_base.
"""
from __future__ import annotations

import numpy as np


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
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    keep = int(min(modes, np.sum(s > 1e-10 * s[0])))
    return np.ascontiguousarray(U[:, :keep])
