"""Tangent damping (Correction.tangent_damping): the stiffness-proportional Rayleigh damping acts
on the corrected tangent. Checked against an independent model (a linear correction that turns
the co-rotated law into another co-rotated law), by finite differences of the damping force, by
energy decay, and the fit's linearised design against the model's own forces."""
import numpy as np
import pytest

from matlearn import _core
from matlearn.learning.fit import FitFrames, RbfParams, fit_system, rbf_kernel
from matlearn.materials import Damping, Material

from learning_cases import assert_energy_decays_from_a_bent_pose
from test_fit import _frames, _scene

E, NU, RHO = 3e5, 0.3, 1000.0


def _lame(E, nu):
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def _equivalent_correction(E2, nu2, tangent_damping):
    """A linear RBF correction A (s - 1) that turns the co-rotated (E, NU) law into (E2, nu2)."""
    mu, lam = _lame(E, NU)
    mu2, lam2 = _lame(E2, nu2)
    A = 2 * (mu2 - mu) * np.eye(3) + (lam2 - lam) * np.ones((3, 3))
    p = RbfParams(np.ones((1, 3)), np.zeros((1, 3)), A, tangent_damping=tangent_damping)
    return p.correction()


def _state(sc, seed=0):
    rng = np.random.default_rng(seed)
    V = np.asarray(sc.mesh.vertices)
    x = V.copy()
    x[:, 1] += 0.25 * V[:, 0] ** 2 / 0.08
    x += 2e-4 * rng.uniform(-1, 1, x.shape)
    return x, 0.3 * rng.standard_normal(x.shape)


@pytest.mark.parametrize("E2,nu2", [(6e5, 0.35), (1e5, 0.25)])
def test_corrected_tangent_damping_equals_the_law_it_turns_the_model_into(E2, nu2):
    damp = Damping(alpha_mass=0.3, alpha_stiffness=0.02)
    sc = _scene(Material("corotated", E, NU, RHO), damp)
    other = _scene(Material("corotated", E2, nu2, RHO), damp).model()
    x, v = _state(sc)
    want_f = np.asarray(other.forces(x, v))
    want_D = other.damping_matrix(x, v).toarray()
    on = sc.model(_equivalent_correction(E2, nu2, True))
    np.testing.assert_allclose(on.forces(x, v), want_f, rtol=0, atol=1e-9 * np.abs(want_f).max())
    np.testing.assert_allclose(on.damping_matrix(x, v).toarray(), want_D, rtol=0,
                               atol=1e-9 * np.abs(want_D).max())
    # without tangent damping the damping force stays the nominal one's: visibly different
    off = sc.model(_equivalent_correction(E2, nu2, False))
    assert np.abs(np.asarray(off.forces(x, v)) - want_f).max() > 1e-3 * np.abs(want_f).max()
    # and the stiffness is the same either way (only the damping changes)
    np.testing.assert_allclose(on.stiffness(x, v, True).toarray(),
                               other.stiffness(x, v, True).toarray(), rtol=0,
                               atol=1e-9 * np.abs(want_D).max() / 0.02)


def test_tangent_damping_matrix_is_the_velocity_derivative_of_a_nonlinear_correction():
    sc = _scene(Material("neo_hookean", E, NU, RHO), Damping(alpha_mass=0.5, alpha_stiffness=0.03))
    rng = np.random.default_rng(3)
    C = 1 + 0.05 * rng.standard_normal((6, 3))
    p = RbfParams(C, rng.normal(0, 3e4, (6, 3)), rng.normal(0, 5e4, (3, 3)),
                  alpha_weights=rng.normal(0, 2e-3, 6), alpha_bias=5e-3, epsilon=0.05,
                  tangent_damping=True)
    model = sc.model(p.correction())
    x, v = _state(sc, seed=4)
    dv = rng.standard_normal(x.shape)
    D = model.damping_matrix(x, v)
    h = 1e-3  # the damping force is linear in v
    fd = (np.asarray(model.forces(x, v + h * dv)) - np.asarray(model.forces(x, v - h * dv))).ravel() / (2 * h)
    Dd = -(D @ dv.ravel())
    np.testing.assert_allclose(fd, Dd, rtol=0, atol=1e-8 * np.abs(Dd).max())
    p.tangent_damping = False
    D_off = sc.model(p.correction()).damping_matrix(x, v)
    assert np.abs((D - D_off) @ dv.ravel()).max() > 1e-3 * np.abs(Dd).max()


def test_tangent_damping_is_passive_energy_never_increases():
    # a strongly softening correction (E 3e5 -> 5e4) with tangent damping: the energy of the law
    # it turns the model into never increases in an unforced, undriven simulation
    damp = Damping(alpha_mass=0.0, alpha_stiffness=0.01)
    sc = _scene(Material("corotated", E, NU, RHO), damp)
    soft = _scene(Material("corotated", 5e4, 0.3, RHO), damp)
    model = sc.model(_equivalent_correction(5e4, 0.3, True))
    assert_energy_decays_from_a_bent_pose(sc, model, soft)


def _theta(p: RbfParams) -> np.ndarray:
    """The fit's unknown layout (fit_normal_equations.hpp) of an RbfParams."""
    return np.concatenate([np.concatenate([p.weights[:, k], p.linear[k]]) for k in range(3)]
                          + [p.alpha_weights, [p.alpha_bias]])


def test_fit_design_is_exact_at_the_current_model_and_second_order_around_it():
    # Rows of the fit: the force a correction theta adds over the nominal model. With tangent
    # damping its damping part (alpha_K + dalpha) K(nominal + correction) v is bilinear; the
    # design is its linearisation at the current model. So with the current model's forces as
    # data its residual is zero at theta_cur, and with a model theta_cur + t d as data it
    # shrinks like t^2 (squared: t^4), not t (squared: t^2).
    sc = _scene(Material("corotated", E, NU, RHO), Damping(0.0, 0.01))
    nominal = sc.model()
    rng = np.random.default_rng(1)
    c, eps = 5, 0.05
    C = 1 + 0.05 * rng.standard_normal((c, 3))
    g1 = rbf_kernel(np.ones((1, 3)), C, eps)[0]

    def params(W, A, wa, a0):
        return RbfParams(C, W, A, -(W.T @ g1), wa, a0, eps, clamp=False, tangent_damping=True)

    A = rng.normal(0, 5e4, (3, 3))
    cur = params(rng.normal(0, 1e4, (c, 3)), 0.5 * (A + A.T), rng.normal(0, 2e-3, c), 4e-3)
    d = params(rng.normal(0, 1e4, (c, 3)), rng.normal(0, 5e4, (3, 3)), rng.normal(0, 2e-3, c), 2e-3)
    current = sc.model(cur.correction())
    X, Vel = _frames(sc, nominal, steps=30)
    n = sc.mesh.num_vertices
    free = np.ones(3 * n, bool)
    free[(3 * sc.fixed[:, None] + np.arange(3)).ravel()] = False

    def residual(q: RbfParams, tangent=True):
        """|design theta_q - data|^2 with the model of q as data, and |data|^2."""
        target = sc.model(q.correction())
        fc = np.stack([np.asarray(target.forces(x, v)) - np.asarray(current.forces(x, v))
                       for x, v in zip(X, Vel)])
        N, rhs, yy, _ = _core.fit.normal_equations(nominal, current, X, Vel, fc, None, free, C, eps,
                                                   None, None, True, tangent)
        th = _theta(q)
        return abs(yy - 2 * th @ rhs + th @ N @ th), yy

    r0, yy0 = residual(cur)
    assert yy0 > 0 and r0 <= 1e-12 * yy0
    res = [residual(params(cur.weights + t * d.weights, cur.linear + t * d.linear,
                           cur.alpha_weights + t * d.alpha_weights,
                           cur.alpha_bias + t * d.alpha_bias))[0] for t in (0.2, 0.1)]
    assert res[0] / res[1] > 10, res  # ~16 (second order); a first-order error gives ~4
    with pytest.raises(Exception, match="tangent damping"):
        residual(cur, tangent=False)


def test_fit_system_carries_the_flag_into_the_fitted_params():
    sc = _scene(Material("corotated", E, NU, RHO), Damping(0.0, 0.01))
    nominal = sc.model()
    X, Vel = _frames(sc, nominal, steps=30)
    fr = FitFrames(X, Vel, np.zeros(X.shape), None, sc.fixed)
    from matlearn.learning.fit import solve_fit

    for on in (True, False):
        p, _ = solve_fit(fit_system(nominal, [fr], 4, tangent_damping=on))
        assert p.tangent_damping is on and p.correction().tangent_damping is on
        q = RbfParams.from_arrays(p.to_arrays())
        assert q.tangent_damping is on


@pytest.mark.parametrize("on", [True, False])
def test_saved_runs_keep_the_flag_for_the_rbf_and_the_mlp(tmp_path, on):
    from matlearn.learning.io import load_model, save_model

    rng = np.random.default_rng(0)
    mlp = {"layers": [(rng.normal(size=(4, 6)), np.zeros(4))], "in_mean": np.zeros(6),
           "in_std": np.ones(6), "out_mean": np.zeros(4), "out_std": np.ones(4)}
    save_model(tmp_path, RbfParams(np.ones((1, 3)), np.zeros((1, 3)), tangent_damping=on), mlp)
    assert load_model(tmp_path, "rbf").tangent_damping is on
    assert load_model(tmp_path, "mlp").tangent_damping is on
