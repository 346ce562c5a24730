"""The speed paths of issue 3 give the results of the paths they replace, within stated tolerances:
reused factorisations (chord iterations) in the backward-Euler step, the reduced tangents of the
space-time Jacobian, and the frame stride of its tangent evaluations."""
import numpy as np
import pytest

from matlearn import _core, materials, meshes
from matlearn.learning.spacetime import build_problem, solve_spacetime
from matlearn.recording import Recording
from matlearn.scene import Scene


def _bar_model(material="corotated", damping=(0.5, 0.005)):
    mesh = meshes.bar(0.1, 0.02, 0.02, cells=(8, 2, 2))
    model = materials.make_model(mesh, materials.Material(material, 2e5, 0.4, 1000.0),
                                 materials.Damping(*damping))
    fixed = np.flatnonzero(np.asarray(mesh.vertices)[:, 0] < 1e-9)
    return mesh, model, fixed


@pytest.mark.parametrize("material", ["corotated", "neo_hookean"])
def test_reused_factorisation_matches_newton(material):
    mesh, model, fixed = _bar_model(material)
    V = np.asarray(mesh.vertices)
    f = np.zeros_like(V)
    f[V[:, 0] > 0.099, 1] = -0.05
    g = np.array([0.0, 0.0, -9.81])
    runs = {}
    for reuse in (False, True):
        integ = _core.time.Integrator(model, fixed, 1e-3, g, reuse_factorization=reuse, extrapolate=reuse)
        X, factorizations, iterations = [], 0, 0
        for _ in range(150):
            integ.step(f)
            X.append(integ.x.copy())
            factorizations += integ.last_timings["factorizations"]
            iterations += integ.last_timings["iterations"]
        runs[reuse] = (np.array(X), factorizations, iterations)
    X0, f0, it0 = runs[False]
    X1, f1, it1 = runs[True]
    assert f0 == it0  # Newton: one factorisation per iteration
    assert f1 < 0.5 * f0, (f1, f0)  # the factor is reused most of the time
    disp = np.abs(X0 - V[None]).max()
    assert disp > 1e-3  # the bar really moves (bends, swings)
    rel = np.abs(X1 - X0).max() / disp
    assert rel < 1e-6, rel


def test_linearised_step_ignores_reuse_and_extrapolation():
    # max_newton = 1 is the linearised step: one solve with the current tangent, from v_n.
    mesh, model, fixed = _bar_model()
    g = np.array([0.0, 0.0, -9.81])
    out = []
    for reuse in (False, True):
        integ = _core.time.Integrator(model, fixed, 1e-3, g, max_newton=1, reuse_factorization=reuse,
                                      extrapolate=reuse)
        X, _ = integ.simulate(30, np.zeros((mesh.num_vertices, 3)), 1)
        out.append(X)
    np.testing.assert_array_equal(out[0], out[1])


def test_reduced_tangents_equal_projected_assembled_operators():
    mesh, model, fixed = _bar_model(damping=(0.5, 0.005))
    rng = np.random.default_rng(3)
    V = np.asarray(mesh.vertices)
    x = V + 2e-3 * rng.standard_normal(V.shape)
    x[fixed] = V[fixed]
    v = 0.1 * rng.standard_normal(V.shape)
    phi = rng.standard_normal((3 * len(V), 7))
    Kr, Dr = model.reduced_tangents(x, phi)
    K = model.stiffness(x, v, project_psd=False)
    D = model.damping_matrix(x, v)
    np.testing.assert_allclose(Kr, phi.T @ (K @ phi), rtol=0, atol=1e-11 * np.abs(Kr).max())
    np.testing.assert_allclose(Dr, phi.T @ (D @ phi), rtol=0, atol=1e-11 * np.abs(Dr).max())
    with pytest.raises(ValueError):
        model.reduced_tangents(x, phi[:-1])


def _spacetime_case(steps=60):
    mesh = meshes.bar(0.06, 0.02, 0.02, cells=(3, 1, 1))
    V = np.asarray(mesh.vertices)
    sc = Scene(mesh=mesh, material=materials.Material("corotated", 2e5, 0.4, 1000.0),
               damping=materials.Damping(0.5, 0.002), fixed=np.flatnonzero(V[:, 0] < 1e-9), time_step=1e-3)
    model = sc.model()
    integ = sc.integrator(model, max_newton=30, tolerance=1e-12)
    integ.set_state(V, np.zeros_like(V))
    X, _ = integ.simulate(steps, np.zeros_like(V), 1)
    rec = Recording(np.arange(steps + 1) * sc.time_step, V.copy(), X.copy(), at_rest_initially=True)
    free = np.setdiff1d(np.arange(len(V)), sc.fixed)
    dofs = (3 * free[:, None] + np.arange(3)).ravel()
    phi = np.zeros((3 * len(V), len(dofs)))
    phi[dofs, np.arange(len(dofs))] = 1.0
    return sc, model, rec, X, phi


def test_tangent_stride_shares_the_middle_frame_tangent():
    sc, model, rec, X, phi = _spacetime_case(steps=20)
    P1 = build_problem(sc, model, rec, phi, 1.0).problem
    P4 = build_problem(sc, model, rec, phi, 1.0).problem
    P4.tangent_stride = 4
    assert P4.tangent_stride == 4
    rng = np.random.default_rng(0)
    Z = build_problem(sc, model, rec, phi, 1.0).project(X) + 1e-4 * rng.standard_normal((P1.frames, P1.modes))
    P1.linearize(Z)
    P4.linearize(Z)
    r, nb = P1.modes, P1.frames - 2
    # physics row block b depends on frames b, b+1, b+2; probe its d/dz_{b+2} block (A_b).
    def block(P, b):
        out = []
        for c in range(r):
            p = np.zeros(P.num_unknowns)
            p[(b + 2) * r + c] = 1.0
            out.append(P.jvp(p)[b * r:(b + 1) * r])
        return np.array(out).T
    for b in range(nb):
        mid = min(b - b % 4 + 2, nb - 1)
        np.testing.assert_allclose(block(P4, b), block(P1, mid), rtol=1e-12, atol=0)
    with pytest.raises(ValueError):
        P4.tangent_stride = 0


def test_tangent_stride_reaches_the_same_trajectory():
    # Exact model, all vertices observed: both solves recover the truth; stride 5 only changes
    # the Gauss-Newton directions, not the minimiser.
    sc, model, rec, X, phi = _spacetime_case()
    X0 = np.repeat(np.asarray(sc.mesh.vertices)[None], len(X), axis=0)
    errs = []
    for k in (1, 5):
        setup = build_problem(sc, model, rec, phi, 1.0)
        setup.problem.tangent_stride = k
        out = solve_spacetime(setup, X0, iterations=8, tolerance=1e-9)
        errs.append(np.abs(out["X"] - X).max() / np.abs(X - X0).max())
    assert errs[0] < 1e-4, errs
    assert errs[1] < 1e-4, errs
