"""RbfCorrection's isotropic blend (isotropic_width > 0; the shared isotropic_blend of
cpp/correction/isotropy.*, as MlpCorrection's):

* a fitted RBF is not isotropic (dPh_1 != dPh_2 at s_1 = s_2); blended, its outputs are equal at
  coincident stretches, bitwise the raw RBF where every gap is >= the width, the mean of dPh and
  dalpha are kept, and the Jacobians pass a central finite-difference check inside the blend;
* the values-only path is bitwise the full path's values, inside and outside the kernel box;
* the default (0) is the raw RBF; < 0 is 0.1 x the centres' mean per-axis std; a non-finite
  width raises ValueError.
"""
import numpy as np
import pytest

from matlearn import _core

from isotropy_checks import check_blend, coincident_states, fd_rows


def _rbf(width, box=0.3, seed=3):
    """A random RBF with a damping part; its kernel box [1 - box, 1 + box]^3."""
    rng = np.random.default_rng(seed)
    c = 1 + 0.08 * rng.standard_normal((12, 3))
    args = (c, 2e3 * rng.standard_normal((12, 3)), 5e3 * rng.standard_normal((3, 3)),
            100 * rng.standard_normal(3), 0.01 * rng.standard_normal(12), 0.002, 0.05)
    lo, hi = np.full(3, 1 - box), np.full(3, 1 + box)
    return (_core.correction.RbfCorrection(*args, lower=lo, upper=hi, isotropic_width=width),
            _core.correction.RbfCorrection(*args, lower=lo, upper=hi))


def test_rbf_stress_is_consistent_at_coincident_stretches():
    w = 0.02
    rbf, raw = _rbf(w)
    assert raw.isotropic_width == 0.0 and rbf.isotropic_width == w  # default: off
    Fh, g = coincident_states(w, 300, 4)
    Z = np.zeros_like(Fh)
    P, J, Jd, dal = (np.asarray(a) for a in rbf.evaluate(Fh, Z))
    Pr, _, _, dal_r = (np.asarray(a) for a in raw.evaluate(Fh, Z))
    far = check_blend(P, Pr, dal, dal_r, g, w)
    assert not np.array_equal(P[~far], Pr[~far])
    assert np.all(Jd == 0)  # rate-independent
    h = 1e-5 * w
    inside = fd_rows(g, w, h, far)
    for j in range(3):
        dp, dm = Fh.copy(), Fh.copy()
        dp[:, j] += h
        dm[:, j] -= h
        fd = (np.asarray(rbf.evaluate(dp, Z)[0]) - np.asarray(rbf.evaluate(dm, Z)[0])) / (2 * h)
        err = np.abs(fd - J[:, :, j])[inside]
        assert err.max() <= 1e-5 * np.abs(J[inside]).max(), (j, err.max())
    # Without the blend's derivative term (J = the raw Jacobian blended like the values) the FD
    # check would fail: the term matters where the gaps are inside the width.
    Jr = np.asarray(raw.evaluate(Fh, Z)[1])
    assert np.abs(J - Jr)[inside & ~far].max() > 1e-2 * np.abs(J[inside]).max()


def test_rbf_blend_values_path_is_bitwise_the_full_path():
    w = 0.03
    rbf, _ = _rbf(w, box=0.08)  # a tight box: many states beyond it (the kernel extension)
    Fh, _ = coincident_states(w, 400, 9, spread=0.1)
    lo, hi = 0.92, 1.08
    outside = np.any((Fh < lo) | (Fh > hi), axis=1)
    assert 50 < outside.sum() < 350
    Z = np.zeros_like(Fh)
    P, _, _, dal = rbf.evaluate(Fh, Z)
    Pv, dalv = rbf.evaluate_values(Fh, Z)
    np.testing.assert_array_equal(np.asarray(Pv), np.asarray(P))
    np.testing.assert_array_equal(np.asarray(dalv), np.asarray(dal))


def test_rbf_blended_model_forces_do_not_depend_on_the_principal_frame():
    # One element stretched by diag(s, s, t): any rotation of the first two axes is a valid
    # principal frame. The raw RBF's force depends on which one the SVD picks; blended, the
    # correction force is that of a frame-independent stress, so it must be the rotation's image.
    w = 0.02
    rbf, raw = _rbf(w)
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.1
    mesh = _core.fem.TetMesh(V, np.array([[0, 1, 2, 3]]))
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    F = R @ np.diag([1.05, 1.05, 0.97]) @ R.T  # symmetric: eigen-frame rotated in the 1-2 plane
    x = V @ F.T
    v = np.zeros_like(x)

    def corr_force(c):
        m_c = _core.fem.Model(mesh, "neo_hookean", np.array([1e4]), np.array([2e4]), np.array([1e3]))
        m_0 = _core.fem.Model(mesh, "neo_hookean", np.array([1e4]), np.array([2e4]), np.array([1e3]))
        m_c.correction = c
        return np.asarray(m_c.forces(x, v)) - np.asarray(m_0.forces(x, v))

    # the isotropic part of the correction, evaluated in the frame where F is diagonal
    P = np.asarray(rbf.evaluate(np.array([[1.05, 1.05, 0.97]]), np.zeros((1, 3)))[0])[0]
    Pr = np.asarray(raw.evaluate(np.array([[1.05, 1.05, 0.97]]), np.zeros((1, 3)))[0])[0]
    assert abs(Pr[0] - Pr[1]) > 1.0 and abs(P[0] - P[1]) < 1e-8 * np.abs(Pr).max()  # (the cap 1e8)
    vol = 0.1 ** 3 / 6
    Bm = np.linalg.inv((V[1:] - V[0]).T)

    def frame_free_force(p):  # the force of the stress R diag(p) R^T (U = V = R, a valid frame)
        f = -vol * (R @ np.diag(p) @ R.T) @ Bm.T  # columns: forces on vertices 1..3
        return np.vstack([-f.sum(1), f.T])

    want = frame_free_force(P)
    np.testing.assert_allclose(corr_force(rbf), want, rtol=0, atol=1e-7 * np.abs(want).max())
    # the raw RBF's force is off it (the SVD's frame is not R): the check can fail
    want_r = frame_free_force(Pr)
    assert np.abs(corr_force(raw) - want_r).max() > 1e-2 * np.abs(want_r).max()


def test_rbf_isotropic_width_auto_and_bad():
    rbf, _ = _rbf(-1.0)
    c = 1 + 0.08 * np.random.default_rng(3).standard_normal((12, 3))  # _rbf's centres
    assert rbf.isotropic_width == pytest.approx(0.1 * np.mean(c.std(axis=0)), rel=1e-12)
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(ValueError, match="isotropic_width"):
            _rbf(bad)


def test_rbf_params_switch(monkeypatch):
    # learning builds every RbfCorrection through RbfParams.correction(): off by default, on
    # (here the automatic width) through fit.RBF_ISOTROPIC_WIDTH
    from matlearn.learning import fit
    c = 1 + 0.08 * np.random.default_rng(3).standard_normal((12, 3))
    p = fit.RbfParams(centers=c, weights=np.ones((12, 3)))
    assert p.correction().isotropic_width == 0.0
    monkeypatch.setattr(fit, "RBF_ISOTROPIC_WIDTH", -1.0)
    assert p.correction().isotropic_width == pytest.approx(0.1 * np.mean(c.std(axis=0)), rel=1e-12)
