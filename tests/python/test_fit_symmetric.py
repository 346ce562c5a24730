"""The permutation-equivariant RBF fit (learning/fit.py `symmetric`): centres over the 6
permutations of orbit representatives, weights tied so that dPh(Q s) = Q dPh(s) by construction."""
import itertools

import numpy as np
import pytest

from matlearn.learning.fit import FitFrames, fit_correction, fit_system, solve_fit

from test_fit import analytic_forces

A_COEF = 2e6


@pytest.fixture(scope="module")
def analytic_case():
    """Exact control forces of an isotropic analytic correction dP_i = a (s_i - 1)^2 on top of the
    nominal co-rotated law (test_fit.analytic_forces)."""
    sc, nominal, X, Vel, fc = analytic_forces(A_COEF)
    return sc, nominal, [FitFrames(X, Vel, fc, None, sc.fixed)], X, Vel


def _equivariance_error(corr, S):
    """Max relative deviation from dPh(Q s) = Q dPh(s), J(Q s) = Q J(s) Q^T, dalpha(Q s) = dalpha(s)
    over the 6 permutations Q, at stretches S (k, 3)."""
    P0, J0, _, a0 = (np.asarray(o) for o in corr.evaluate(S, np.zeros_like(S)))
    err = 0.0
    for pi in map(list, itertools.permutations(range(3))):
        P, J, _, a = (np.asarray(o) for o in corr.evaluate(np.ascontiguousarray(S[:, pi]), np.zeros_like(S)))
        err = max(err, np.abs(P - P0[:, pi]).max() / np.abs(P0).max(),
                  np.abs(J - J0[:, pi][:, :, pi]).max() / np.abs(J0).max(),
                  np.abs(a - a0).max() / max(np.abs(a0).max(), 1e-300))
    return err


def test_symmetric_fit_is_permutation_equivariant_inside_and_beyond_the_data(analytic_case):
    sc, nominal, frames, _, _ = analytic_case
    rng = np.random.default_rng(3)
    # stretches inside the fitted range, well beyond it (the box extension), and coincident pairs
    S = np.r_[1 + 0.05 * rng.standard_normal((150, 3)), 1 + 0.4 * rng.standard_normal((150, 3))]
    S[:20, 1] = S[:20, 0]
    S = np.ascontiguousarray(S)
    raw, _ = fit_correction(nominal, frames, num_centers=8, damping=True, ridge=1e-10, smooth=1e-3)
    sym, info = fit_correction(nominal, frames, num_centers=8, damping=True, ridge=1e-10, smooth=1e-3,
                               symmetric=True)
    assert info["symmetric"] and len(sym.centers) == 6 * 8
    assert _equivariance_error(raw.correction(), S) > 1e-3  # an unconstrained fit is not
    assert _equivariance_error(sym.correction(), S) < 1e-12
    P = np.asarray(sym.correction().evaluate(S[:20], np.zeros((20, 3)))[0])
    np.testing.assert_allclose(P[:, 0], P[:, 1], rtol=0, atol=1e-12 * np.abs(P).max())
    lo, hi = sym.box()
    assert np.ptp(lo) == 0 and np.ptp(hi) == 0  # the box is the same on every axis


def test_symmetric_fit_reproduces_an_isotropic_correction_and_keeps_its_centres(analytic_case):
    sc, nominal, frames, X, Vel = analytic_case
    system = fit_system(nominal, frames, num_centers=24, damping=False, symmetric=True)
    p, info = solve_fit(system, 1e-10)
    Fh = np.concatenate([np.asarray(nominal.principal_kinematics(x, v)[0]) for x, v in zip(X, Vel)])
    got = np.asarray(p.correction().evaluate(Fh, np.zeros_like(Fh))[0])
    want = A_COEF * (Fh - 1) ** 2
    span = np.abs(want).max()
    # measured: rms 0.14 % of the range, residual ratio 0.019 (the unconstrained fit with 24
    # centres: 0.17 %, 0.021)
    assert np.sqrt(np.mean((got - want) ** 2)) < 0.005 * span
    assert info["residual_ratio"] < 0.05
    # the reduced problem is the full one on T's range: same residual at the expanded parameters
    T = system.transform
    assert T.shape == (3 * (6 * 24 + 3), 3 * 24 + 2)
    full = fit_system(nominal, frames, centers=(p.centers, p.epsilon), damping=False)
    theta = np.concatenate([np.c_[p.weights[:, a][None], p.linear[a][None]].ravel() for a in range(3)])
    res2 = full.yy - 2 * theta @ full.rhs + theta @ full.N @ theta
    assert np.sqrt(res2 / full.yy) == pytest.approx(info["residual_ratio"], rel=1e-6)
    # refitting on the fitted (expanded) centres finds the same orbits in the same order, so
    # iterations can blend corrections entry by entry
    again = fit_system(nominal, frames, centers=(p.centers, p.epsilon), damping=False, symmetric=True)
    assert np.array_equal(again.centers, p.centers)
