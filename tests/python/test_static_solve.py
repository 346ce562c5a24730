"""Integrator.static_solve: Newton with chord steps (the last factorised tangent reused while it
contracts the residual) reaches the stated residual tolerance, measured here independently from
Model.forces, with and without a learned correction. With a correction the factorised tangent is
only the symmetric part of dN/dFh, so Newton converges linearly and most steps are chord steps."""
import numpy as np
import pytest

from matlearn import _core, materials, meshes

G = np.array([0.0, -9.81, 0.0])


def _rest_free_rbf(seed=0):
    """RBF correction with a non-symmetric Jacobian (random linear part) and no rest stress."""
    rng = np.random.default_rng(seed)
    c = 1.0 + 0.05 * rng.standard_normal((5, 3))
    w = 2e3 * rng.standard_normal((5, 3))
    A = 2e4 * rng.standard_normal((3, 3))
    eps = 0.05
    phi1 = np.sqrt(((1.0 - c) ** 2).sum(axis=1) + eps ** 2)
    b = -(w * phi1[:, None]).sum(axis=0)  # dPh(1, 1, 1) = 0
    return _core.correction.RbfCorrection(c, w, A, b, np.zeros(0), 0.0, eps)


def _setup(corrected: bool):
    mesh = meshes.bar(0.1, 0.02, 0.02, cells=(8, 2, 2))
    model = materials.make_model(mesh, materials.Material("neo_hookean", 1e5, 0.4, 1000.0),
                                 materials.Damping(0.0, 0.0))
    if corrected:
        model.correction = _rest_free_rbf()
    V = np.asarray(mesh.vertices)
    fixed = np.flatnonzero(V[:, 0] < 1e-9)
    integ = _core.time.Integrator(model, fixed, 1e-3, G)
    return model, integ, fixed


def _residual(model, x, fixed, f_ext):
    """|f_int(x) + f_ext + m g| on the free DOFs and the load norm |f_ext + m g| (all DOFs)."""
    load = f_ext + np.asarray(model.vertex_mass)[:, None] * G
    r = np.asarray(model.forces(x, np.zeros_like(x))) + load
    r[fixed] = 0.0
    return np.linalg.norm(r), np.linalg.norm(load)


@pytest.mark.parametrize("corrected", [False, True])
def test_static_solve_reaches_tolerance(corrected):
    model, integ, fixed = _setup(corrected)
    n = len(model.vertex_mass)
    f = np.zeros((n, 3))
    f[np.argmax(np.asarray(model.mesh.vertices)[:, 0])] = [0.0, -0.05, 0.02]  # a tip force (N)
    tol = 1e-9
    integ.static_solve(f, load_steps=2, tolerance=tol)
    x = np.array(integ.x)
    r, ref = _residual(model, x, fixed, f)
    sag = np.abs(x - np.asarray(model.mesh.vertices)).max()
    assert sag > 1e-3  # a real deformation (m)
    assert r <= tol * ref
    stats = integ.last_static_iterations
    assert stats["factorizations"] >= 1
    if corrected:
        # linear Newton convergence: chord steps carry most of the iteration
        assert stats["iterations"] > 2 * stats["factorizations"]
    # the same equilibrium as a much tighter solve from the result
    integ.set_state(x, np.zeros_like(x))
    integ.static_solve(f, load_steps=1, tolerance=1e-12)
    assert np.abs(np.array(integ.x) - x).max() <= 1e-6 * sag
