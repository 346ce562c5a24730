"""Sparse reduced space-time problem (C++ `_core.spacetime`) and its Python wrapper."""
import numpy as np
import pytest

from matlearn import meshes
from matlearn.learning.spacetime import build_problem, solve_spacetime
from matlearn.materials import Damping, Material
from matlearn.recording import Recording
from matlearn.scene import Scene

L = 0.06


def _scene(material=None, damping=None, cells=(3, 1, 1)):
    mesh = meshes.bar(L, 0.02, 0.02, cells=cells)
    V = np.asarray(mesh.vertices)
    fixed = np.flatnonzero(V[:, 0] < 1e-9)
    return Scene(mesh=mesh, material=material or Material("corotated", 2e5, 0.4, 1000.0),
                 damping=damping or Damping(0.5, 0.0), fixed=fixed, time_step=1e-3)


def _truth(scene, model, steps=40, times=None):
    """Simulate released from rest under gravity; markers on every vertex."""
    V = np.asarray(scene.mesh.vertices)
    n = len(V)
    integ = scene.integrator(model, max_newton=30, tolerance=1e-12)
    integ.set_state(V, np.zeros((n, 3)))
    X, Vel = integ.simulate(steps, np.zeros((n, 3)), 1)
    t = np.arange(steps + 1) * scene.time_step
    if times is None:
        return X, Vel, Recording(t, V.copy(), X.copy(), at_rest_initially=True)
    from matlearn.replay import interpolate_frames

    return X, Vel, Recording(times, V.copy(), interpolate_frames(t, X, times), at_rest_initially=True)


def _full_basis(scene):
    """Identity on the free DOFs: the reduced problem is the full problem."""
    n = scene.mesh.num_vertices
    free = np.setdiff1d(np.arange(n), scene.fixed)
    dofs = (3 * free[:, None] + np.arange(3)).ravel()
    phi = np.zeros((3 * n, len(dofs)))
    phi[dofs, np.arange(len(dofs))] = 1.0
    return phi


def test_jacobian_products_pass_fd_and_adjoint_checks():
    # alpha_K = 0: the Jacobian is then exact (it omits d(alpha_K K v)/dx, a third-order term).
    sc = _scene()
    model = sc.model()
    X, _, rec = _truth(sc, model, steps=12)
    phi = _full_basis(sc)[:, ::2]  # a genuine reduction
    setup = build_problem(sc, model, rec, phi, 1.0)
    P = setup.problem
    rng = np.random.default_rng(1)
    Z = setup.project(X) + 1e-4 * rng.standard_normal((P.frames, P.modes))
    P.linearize(Z)
    p = rng.standard_normal(P.num_unknowns)
    q = rng.standard_normal(P.num_residuals)
    Jp = P.jvp(p)
    eps = 1e-6
    dZ = p.reshape(Z.shape)
    fd = (P.residual(Z + eps * dZ) - P.residual(Z - eps * dZ)) / (2 * eps)
    assert np.linalg.norm(fd - Jp) <= 1e-6 * np.linalg.norm(Jp), np.linalg.norm(fd - Jp) / np.linalg.norm(Jp)
    assert p @ P.vjp(q) == pytest.approx(Jp @ q, rel=1e-10)


def test_linear_step_agrees_with_dense_lstsq():
    sc = _scene(damping=Damping(0.5, 0.002))
    model = sc.model()
    X, _, rec = _truth(sc, model, steps=10)
    phi = _full_basis(sc)[:, ::3]
    setup = build_problem(sc, model, rec, phi, 1.0)
    P = setup.problem
    Z = np.zeros((P.frames, P.modes))
    P.linearize(Z)
    J = np.stack([P.jvp(e) for e in np.eye(P.num_unknowns)], axis=1)  # dense only in this test
    C = P.residual(Z)
    ref = np.linalg.lstsq(J, -C, rcond=None)[0]
    for solver in ("pcgls", "direct", "cgls"):
        dz, _ = P.solve_linear(solver, 3000, 1e-12)
        np.testing.assert_allclose(dz, ref, rtol=0, atol=1e-6 * np.abs(ref).max(), err_msg=solver)


@pytest.mark.parametrize("solver", ["lm", "pcgls"])
@pytest.mark.parametrize("lam", [0.01, 1.0, 1e4])
def test_recovers_known_trajectory_when_model_exact(lam, solver):
    sc = _scene()
    model = sc.model()
    X, _, rec = _truth(sc, model, steps=40)
    setup = build_problem(sc, model, rec, _full_basis(sc), lam)
    start = np.repeat(np.asarray(sc.mesh.vertices)[None], len(X), axis=0)  # rest: far from truth
    out = solve_spacetime(setup, start, iterations=15, tolerance=1e-12, solver=solver)
    size = meshes.object_size(sc.mesh)
    assert np.abs(out["X"] - X).max() < 1e-6 * size
    # Control forces ~ 0: tiny against the weight of a vertex.
    weight = np.asarray(model.vertex_mass).max() * 9.81
    assert np.abs(out["control_forces"]).max() < 1e-4 * weight


def test_samples_between_steps_are_interpolated():
    sc = _scene()
    model = sc.model()
    times = 0.0005 + 0.004 * np.arange(10)  # 250 Hz, half a step off the simulation grid
    X, _, rec = _truth(sc, model, steps=40, times=times)
    assert rec.times[0] > 0
    # The problem starts at times[0]: compare with the truth resampled on its frames.
    setup = build_problem(sc, model, rec, _full_basis(sc), 1.0)
    from matlearn.replay import interpolate_frames

    t = np.arange(41) * 1e-3
    Xt = interpolate_frames(t, X, setup.times)
    out = solve_spacetime(setup, np.repeat(np.asarray(sc.mesh.vertices)[None], len(setup.times), 0),
                          iterations=15, tolerance=1e-12)
    # Linear interpolation of the truth between steps is itself only O(h^2) accurate.
    assert np.abs(out["X"] - Xt).max() < 2e-3 * meshes.object_size(sc.mesh)


def test_control_forces_equal_truth_minus_nominal_force():
    truth_sc = _scene(Material("neo_hookean", 2e5, 0.4, 1000.0))
    X, _, rec = _truth(truth_sc, truth_sc.model(), steps=40)
    nominal_sc = _scene(Material("corotated", 3e5, 0.4, 1000.0))
    nominal = nominal_sc.model()
    setup = build_problem(nominal_sc, nominal, rec, _full_basis(nominal_sc), 1e3)
    out = solve_spacetime(setup, X, iterations=10, tolerance=1e-12)
    Xs, Vs, fc = out["X"], out["V"], out["control_forces"]
    truth = truth_sc.model()
    free = np.setdiff1d(np.arange(len(X[0])), nominal_sc.fixed)
    diff = np.stack([np.asarray(truth.forces(Xs[j], Vs[j])) - np.asarray(nominal.forces(Xs[j], Vs[j]))
                     for j in range(2, len(Xs))])[:, free]
    # Stated tolerance: 1% of the largest force difference (the observations pull the
    # trajectory by ~1e-3 of the physics weight at lam = 1e3).
    assert np.abs(fc[:, free] - diff).max() < 1e-2 * np.abs(diff).max()


def test_bad_input_raises():
    sc = _scene()
    model = sc.model()
    _, _, rec = _truth(sc, model, steps=5)
    with pytest.raises(ValueError):
        build_problem(sc, model, rec, np.zeros((7, 2)), 1.0)
    with pytest.raises(ValueError):
        build_problem(sc, model, rec, _full_basis(sc), -1.0)
