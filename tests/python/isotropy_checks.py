"""Shared checks of the isotropic blend at coincident principal stretches (cpp/correction/
isotropy.*), used for both corrections that have it (test_distill: MlpCorrection,
test_rbf_isotropy: RbfCorrection)."""
from __future__ import annotations

import numpy as np


def coincident_states(width, n, seed, spread=0.05):
    """Sorted stretches whose two gaps s_1 - s_2, s_2 - s_3 are drawn in [0, 1.5 width); the first
    6 rows coincide exactly (s_1 = s_2, then all three). Returns (Fh (n, 3), gaps (n, 2))."""
    rng = np.random.default_rng(seed)
    base = 1 + spread * rng.standard_normal((n, 1))
    g = width * rng.uniform(0, 1.5, (n, 2))
    g[:3, 0] = 0
    g[3:6] = 0
    return np.ascontiguousarray(np.c_[base + g[:, :1] + g[:, 1:], base + g[:, 1:], base]), g


def check_blend(P, Pr, dal, dal_r, g, width):
    """The blended outputs P against the raw ones Pr (same states, gaps g): the raw correction is
    not isotropic, the blend is (at s_1 = s_2 and where all three coincide), it leaves every row
    whose gaps are all >= width bitwise alone, keeps the mean of dPh, and leaves dalpha (a scalar,
    isotropic already) unchanged. Returns the mask of those untouched rows."""
    spread = np.abs(Pr).max()
    assert np.abs(Pr[:6, 0] - Pr[:6, 1]).min() > 1e-3 * spread  # the raw correction is not isotropic
    assert np.abs(P[:6, 0] - P[:6, 1]).max() < 1e-8 * spread  # the blend is, at s_1 = s_2 ...
    assert np.abs(P[3:6, 1] - P[3:6, 2]).max() < 1e-8 * spread  # ... and where all three coincide
    far = g.min(1) >= width
    assert far.sum() > 20 and np.array_equal(P[far], Pr[far])  # untouched beyond the width
    np.testing.assert_allclose(P.mean(1), Pr.mean(1), rtol=1e-12, atol=1e-9 * spread)  # mean kept
    np.testing.assert_array_equal(dal, dal_r)
    return far


def fd_rows(g, width, h, far):
    """Rows for a central-difference check of the blend's Jacobian with step h: gaps >= width / 10
    (closer, the blend's 3x3 solve is conditioned up to 3e8 and its round-off, though harmless,
    dominates a difference quotient) and not within 10 h of the width (the blend is C1: its second
    derivative jumps there); at least 100 of them inside the blend."""
    inside = (g.min(1) >= 0.1 * width) & np.all(np.abs(g - width) > 10 * h, axis=1)
    assert (inside & ~far).sum() > 100
    return inside
