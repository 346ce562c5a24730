"""RBF correction fit (learning/fit.py) and passivity of the learned damping."""
import numpy as np
import pytest

from matlearn import _core, meshes
from matlearn.learning.fit import FitFrames, RbfParams, fit_correction, rbf_kernel
from matlearn.materials import Damping, Material
from matlearn.scene import Scene

from learning_cases import assert_energy_decays_from_a_bent_pose


def _scene(material, damping=None):
    mesh = meshes.bar(0.08, 0.02, 0.02, cells=(4, 1, 1))
    V = np.asarray(mesh.vertices)
    return Scene(mesh=mesh, material=material, damping=damping or Damping(0.0, 0.0),
                 fixed=np.flatnonzero(V[:, 0] < 1e-9), time_step=1e-3)


def _frames(sc, model, steps=150):
    """A release from a tip-loaded pose (large bending, 20 %-ish stretches)."""
    n = sc.mesh.num_vertices
    V = np.asarray(sc.mesh.vertices)
    integ = sc.integrator(model)
    f = np.zeros((n, 3))
    tip = V[:, 0] > 0.079
    f[tip, 1] = 0.6 / tip.sum()
    integ.set_state(V, np.zeros((n, 3)))
    integ.static_solve(f, load_steps=4)
    X, Vel = integ.simulate(steps, np.zeros((n, 3)), 1)
    return X[1::3], Vel[1::3]


def analytic_forces(a):
    """Truth = nominal co-rotated + an analytic principal-stress correction dP_i = a (s_i - 1)^2
    (zero at rest): (scene, nominal model, X, Vel, exact control forces = force differences)."""
    sc = _scene(Material("corotated", 3e5, 0.3, 1000.0))
    nominal = sc.model()

    def analytic(Fh, Fhdot):
        Fh = np.asarray(Fh)
        J = np.zeros((len(Fh), 3, 3))
        J[:, [0, 1, 2], [0, 1, 2]] = 2 * a * (Fh - 1)
        return a * (Fh - 1) ** 2, J, None, None

    truth = sc.model(_core.correction.PythonCorrection(analytic))
    X, Vel = _frames(sc, truth)
    fc = np.stack([np.asarray(truth.forces(x, v)) - np.asarray(nominal.forces(x, v)) for x, v in zip(X, Vel)])
    return sc, nominal, X, Vel, fc


def test_rbf_fit_reproduces_analytic_stress_correction_from_exact_forces():
    a = 2e6
    nominal_sc, nominal, X, Vel, fc = analytic_forces(a)
    frames = FitFrames(X, Vel, fc, phi=None, constrained=nominal_sc.fixed)
    params, info = fit_correction(nominal, [frames], num_centers=24, damping=False, ridge=1e-10)
    Fh = np.concatenate([np.asarray(nominal.principal_kinematics(x, v)[0]) for x, v in zip(X, Vel)])
    got = np.asarray(params.correction().evaluate(Fh, np.zeros_like(Fh))[0])
    want = a * (Fh - 1) ** 2
    span = np.abs(want).max()
    assert span > 1e3  # the motion really exercises the correction
    # Stated tolerance: max error 3 %, rms error 0.5 % of the correction's range over the
    # sampled stretches (the tail of the stretch distribution is sampled sparsely).
    assert np.abs(got - want).max() < 0.03 * span, (np.abs(got - want).max(), span)
    assert np.sqrt(np.mean((got - want) ** 2)) < 0.005 * span
    assert info["residual_ratio"] < 0.05
    # Zero at rest by construction.
    np.testing.assert_allclose(params.correction().evaluate(np.ones((1, 3)), np.zeros((1, 3)))[0], 0, atol=1e-6 * span)


def test_fit_recovers_strain_dependent_damping():
    # Truth alpha_K(s1) = 0.01 + 0.2 (s1 - 1); nominal alpha_K = 0.01: the fitted dalpha should
    # follow 0.2 (s1 - 1) on the sampled stretches.
    mat = Material("corotated", 3e5, 0.3, 1000.0)
    nominal_sc = _scene(mat, Damping(0.0, 0.01))
    truth_sc = _scene(mat, Damping(0.0, 0.01, stiffness_poly=[0.2]))
    nominal, truth = nominal_sc.model(), truth_sc.model()
    X, Vel = _frames(nominal_sc, truth)
    fc = np.stack([np.asarray(truth.forces(x, v)) - np.asarray(nominal.forces(x, v)) for x, v in zip(X, Vel)])
    params, _ = fit_correction(nominal, [FitFrames(X, Vel, fc, None, nominal_sc.fixed)], num_centers=16,
                               damping=True, ridge=1e-10)
    Fh = np.concatenate([np.asarray(nominal.principal_kinematics(x, v)[0]) for x, v in zip(X, Vel)])
    got = np.asarray(params.correction().evaluate(Fh, np.zeros_like(Fh))[3])
    want = np.maximum(0.01 + 0.2 * (Fh[:, 0] - 1), 0) - 0.01
    assert np.abs(want).max() > 3e-3
    # Stated tolerance: max 15 %, rms 2 % of the largest alpha change (elastic part ~0 too).
    assert np.abs(got - want).max() < 0.15 * np.abs(want).max()
    assert np.sqrt(np.mean((got - want) ** 2)) < 0.02 * np.abs(want).max()


def test_learned_damping_is_passive_energy_never_increases():
    # A learned damping that is strongly negative in places (alpha_bias -1 s): the C++ clamps
    # alpha_K + dalpha at 0, so an unforced, undriven, gravity-free simulation never gains energy.
    sc = _scene(Material("corotated", 3e5, 0.3, 1000.0), Damping(0.0, 0.002))
    rng = np.random.default_rng(0)
    C = 1 + 0.2 * rng.standard_normal((6, 3))
    params = RbfParams(C, np.zeros((6, 3)), alpha_weights=rng.normal(0, 1.0, 6), alpha_bias=-1.0, epsilon=0.1)
    model = sc.model(params.correction())
    dal = np.asarray(params.correction().evaluate(C, np.zeros_like(C))[3])
    assert dal.min() < -0.01 and dal.max() > -1  # really negative somewhere
    assert_energy_decays_from_a_bent_pose(sc, model, sc)


def test_rbf_kernel_and_params_roundtrip():
    C = np.array([[1.0, 1.0, 1.0], [1.1, 0.9, 1.0]])
    K = rbf_kernel(np.array([[1.0, 1.0, 1.0]]), C, 0.1)
    np.testing.assert_allclose(K, [[0.1, np.sqrt(0.02 + 0.01)]])
    p = RbfParams(C, np.ones((2, 3)), alpha_weights=np.ones(2), alpha_bias=0.5, epsilon=0.1)
    q = RbfParams.from_arrays(p.to_arrays())
    np.testing.assert_array_equal(q.centers, p.centers)
    assert q.alpha_bias == 0.5 and q.clamp
    old = {k: v for k, v in p.to_arrays().items() if k != "rbf_clamp"}  # saved before the clamp
    assert not RbfParams.from_arrays(old).clamp
    with pytest.raises(ValueError):
        fit_correction(None, [])


def _python_normal_equations(nominal, current, fr, C, eps, box, damping):
    """The former per-frame Python accumulation (reference for the C++ one)."""
    c = len(C)
    rest_phi = rbf_kernel(np.ones((1, 3)), C, eps, box)[0]
    p = 3 * (c + 3) + ((c + 1) if damping else 0)
    N, rhs, yy = np.zeros((p, p)), np.zeros(p), 0.0
    n = fr.X.shape[1]
    keep = np.ones(3 * n, bool)
    if fr.constrained is not None:
        keep[(3 * np.asarray(fr.constrained)[:, None] + np.arange(3)).ravel()] = False
    P = fr.phi
    for x, v, f in zip(fr.X, fr.V, fr.fc):
        Fh = np.asarray(nominal.principal_kinematics(x, v)[0])
        Pk = rbf_kernel(Fh, C, eps, box, damping=True)
        feat = np.concatenate([rbf_kernel(Fh, C, eps, box) - rest_phi[None], Fh - 1.0], axis=1)
        B = nominal.force_map(x)
        y = np.asarray(f, float).ravel()
        if current is not None:
            y = y + (np.asarray(current.forces(x, v)) - np.asarray(nominal.forces(x, v))).ravel()
        cols = []
        for comp in range(3):
            Bk = B[:, comp::3]
            cols.append((Bk.T @ P).T @ feat if P is not None else Bk[keep] @ feat)
        if damping:
            G = nominal.stiffness_damping_map(x, v)
            Q = np.concatenate([Pk, np.ones((len(Pk), 1))], axis=1)
            cols.append((G.T @ P).T @ Q if P is not None else G[keep] @ Q)
        D = np.concatenate(cols, axis=1)
        yr = P.T @ y if P is not None else y[keep]
        N += D.T @ D
        rhs += D.T @ yr
        yy += yr @ yr
    return N, rhs, yy


@pytest.mark.parametrize("use_basis", [False, True])
@pytest.mark.parametrize("clamp", [False, True])
def test_cpp_normal_equations_match_python_reference(use_basis, clamp):
    sc = _scene(Material("corotated", 3e5, 0.3, 1000.0), Damping(0.0, 0.01))
    nominal = sc.model()
    rng = np.random.default_rng(1)
    C = 1 + 0.05 * rng.standard_normal((5, 3))
    cur = RbfParams(C, rng.normal(0, 1e4, (5, 3)), alpha_weights=rng.normal(0, 1e-3, 5), epsilon=0.05)
    current = sc.model(cur.correction())
    X, Vel = _frames(sc, nominal, steps=12)
    fc = rng.normal(0, 1e-2, X.shape)
    n = sc.mesh.num_vertices
    phi = np.linalg.qr(rng.standard_normal((3 * n, 4)))[0] if use_basis else None
    fr = FitFrames(X, Vel, fc, phi, sc.fixed)
    box = (C.min(0) - 0.01, C.max(0) + 0.01) if clamp else (None, None)
    for cm, damping in ((current, True), (None, False)):
        want = _python_normal_equations(nominal, cm, fr, C, 0.05, box, damping)
        free = None
        if phi is None:
            free = np.ones(3 * n, bool)
            free[(3 * sc.fixed[:, None] + np.arange(3)).ravel()] = False
        got = _core.fit.normal_equations(nominal, cm, X, Vel, fc, phi, free, C, 0.05, box[0], box[1], damping)
        assert got[3] == len(X)
        for g, w in zip(got[:3], want):
            w = np.asarray(w)
            np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-10 * np.abs(w).max())


def test_correction_beyond_training_stretches_is_bounded_and_continuous():
    # Fit the analytic a (s - 1)^2 correction of the first test on its motion, then walk the
    # stretch far beyond the trained range: outside the centres' box the correction is the
    # first-order extension from the nearest box point sc, P(s) = P(sc) + J(sc) (s - sc): it is
    # continuous with a continuous Jacobian (= finite differences) and grows only linearly,
    # with the slope at the edge of the data.
    a = 2e6
    sc = _scene(Material("corotated", 3e5, 0.3, 1000.0))
    nominal = sc.model()

    def analytic(Fh, Fhdot):
        Fh = np.asarray(Fh)
        J = np.zeros((len(Fh), 3, 3))
        J[:, [0, 1, 2], [0, 1, 2]] = 2 * a * (Fh - 1)
        return a * (Fh - 1) ** 2, J, None, None

    truth = sc.model(_core.correction.PythonCorrection(analytic))
    X, Vel = _frames(sc, truth)
    fc = np.stack([np.asarray(truth.forces(x, v)) - np.asarray(nominal.forces(x, v)) for x, v in zip(X, Vel)])
    params, _ = fit_correction(nominal, [FitFrames(X, Vel, fc, None, sc.fixed)], num_centers=16,
                               damping=False, ridge=1e-8)
    lo, hi = params.box()
    assert hi[0] < 1.4  # the walk below goes far beyond the trained range
    corr = params.correction()
    ev = lambda S: [np.asarray(v) for v in corr.evaluate(S, np.zeros_like(S))[:2]]  # noqa: E731
    t = np.linspace(0.0, 1.0, 2001)
    S = np.stack([1 + 0.8 * t, 1 - 0.2 * t, 1 - 0.2 * t], axis=1)  # stretch 1 -> 1.8
    P, J = ev(S)
    # Continuity: steps between neighbours bounded by the Jacobian's scale times the step.
    assert np.abs(np.diff(P, axis=0)).max() < 2 * np.abs(J).max() * 0.8 / 2000
    # First-order extension from the box: P(s) = P(sc) + J(sc) (s - sc) everywhere.
    Sc = np.clip(S, lo, hi)
    Pc, Jc = ev(Sc)
    np.testing.assert_allclose(P, Pc + np.einsum("kij,kj->ki", Jc, S - Sc), rtol=1e-10,
                               atol=1e-9 * np.abs(P).max())
    outside = np.flatnonzero(np.any(S != Sc, axis=1))
    assert len(outside) > 1000
    # Jacobian = finite differences inside, just outside and far outside the box.
    h = 1e-6
    for idx in (100, outside[0] + 1, len(S) - 1):
        for i in range(3):
            d = np.zeros(3)
            d[i] = h
            fd = (ev((S[idx] + d)[None])[0] - ev((S[idx] - d)[None])[0])[0] / (2 * h)
            np.testing.assert_allclose(J[idx][:, i], fd, rtol=1e-5, atol=1e-6 * np.abs(J).max())
    # The Jacobian is continuous across the box boundary.
    s0, s1 = S[outside[0] - 1], S[outside[0]]
    for _ in range(60):  # bisect to the crossing
        mid = 0.5 * (s0 + s1)
        s0, s1 = (s0, mid) if np.any(np.clip(mid, lo, hi) != mid) else (mid, s1)
    J0, J1 = ev(np.stack([s0, s1]))[1]
    assert np.abs(J1 - J0).max() < 1e-6 * np.abs(J1).max()


def test_kernel_gradients_match_finite_differences_inside_and_beyond_the_box():
    from matlearn.learning.fit import centers_box, kernel_gradients

    rng = np.random.default_rng(0)
    C = 1 + 0.02 * rng.standard_normal((6, 3))
    eps = 0.01
    box = centers_box(C, eps)
    S = np.concatenate([1 + 0.01 * rng.standard_normal((20, 3)), 1 + 0.2 * rng.standard_normal((20, 3))])
    outside = np.any((S < box[0]) | (S > box[1]), axis=1)
    assert 5 < outside.sum() < 40
    G = kernel_gradients(S, C, eps, box)
    h = 1e-7
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        fd = (rbf_kernel(S + d, C, eps, box) - rbf_kernel(S - d, C, eps, box)) / (2 * h)
        np.testing.assert_allclose(G[:, :, i], fd, rtol=1e-5, atol=1e-6)


def test_tangent_penalty_keeps_the_fit_well_conditioned_on_noisy_forces():
    # Control forces are never exact: a modulus change (linear in the stretch) observed with
    # 20 % force noise. Unpenalised, the nearly collinear kernels fit the noise with cancelling
    # weights whose tangent is half the nominal modulus (what blew up the held-out simulation
    # of test_learn_clouds); with the tangent penalty the RBF part's tangent stays a small
    # fraction of it and the fit follows the true correction better beyond the data.
    from matlearn.learning.fit import kernel_gradients

    sc = _scene(Material("corotated", 3e5, 0.3, 1000.0))
    nominal = sc.model()
    truth = _scene(Material("corotated", 2e5, 0.3, 1000.0)).model()
    X, Vel = _frames(sc, truth)
    fc = np.stack([np.asarray(truth.forces(x, v)) - np.asarray(nominal.forces(x, v)) for x, v in zip(X, Vel)])
    rng = np.random.default_rng(1)
    fc = fc + 0.2 * np.sqrt(np.mean(fc**2)) * rng.standard_normal(fc.shape)
    frames = [FitFrames(X, Vel, fc, None, sc.fixed)]
    modulus = float(np.median(2 * np.asarray(nominal.mu) + np.asarray(nominal.lam)))
    S = np.concatenate([np.asarray(nominal.principal_kinematics(x, v)[0]) for x, v in zip(X, Vel)])

    def rbf_tangent(p):  # RMS Frobenius norm of the RBF part's tangent over the data / modulus
        J = np.einsum("kc,ikb->icb", p.weights, kernel_gradients(S, p.centers, p.epsilon, p.box()))
        return float(np.sqrt(np.mean(np.sum(J**2, axis=(1, 2))))) / modulus

    # Beyond the data (s1 up to 1.3; the data reach 1.07) the true correction is the stress
    # difference of the two co-rotated laws.
    t = np.linspace(0, 1, 50)
    far = np.stack([1 + 0.3 * t, np.ones_like(t), np.ones_like(t)], axis=1)
    mu_n, lam_n, mu_t, lam_t = nominal.mu[0], nominal.lam[0], truth.mu[0], truth.lam[0]
    want = 2 * (mu_t - mu_n) * (far - 1) + (lam_t - lam_n) * (far - 1).sum(1, keepdims=True)

    def far_error(p):
        got = np.asarray(p.correction().evaluate(far, np.zeros_like(far))[0])
        return np.abs(got - want).max() / np.abs(want).max()

    raw, _ = fit_correction(nominal, frames, num_centers=24, damping=False, ridge=1e-10)
    smooth, info = fit_correction(nominal, frames, num_centers=24, damping=False, ridge=1e-10, smooth=1.0)
    assert info["smooth"] == 1.0
    # Measured: tangent 0.50 -> 0.05 of the modulus, error beyond the data 103 % -> 42 %.
    assert rbf_tangent(raw) > 0.3
    assert rbf_tangent(smooth) < 0.15 * rbf_tangent(raw)
    assert far_error(smooth) < 0.5 * far_error(raw), (far_error(smooth), far_error(raw))


def test_tangent_margin_flags_a_correction_that_softens_into_instability_beyond_the_data():
    from matlearn.learning.fit import tangent_margin

    mat = Material("corotated", 3e5, 0.3, 1000.0)
    nominal = _scene(mat).model()
    mu, lam = float(nominal.mu[0]), float(nominal.lam[0])
    M = 2 * mu + lam
    C = 1 + 0.01 * np.array([[1.0, 0, -1], [0, 1, 0], [-1, 0, 1]])
    zero = RbfParams(C, np.zeros((3, 3)), epsilon=0.01)
    rng = np.random.default_rng(0)
    probes = 1 + 0.1 * rng.standard_normal((200, 3))  # mostly outside the box of C
    # The co-rotated tangent at small strain is 2 mu I + lam 11^T: smallest eigenvalue 2 mu.
    assert tangent_margin(zero, mat, mu, lam, probes) == pytest.approx(2 * mu / M, rel=0.2)
    # A correction whose linear part removes more than 2 mu from the tangent in one direction
    # is unstable there; one that removes less is not.
    for f, sign in ((1.5, -1), (0.5, 1)):
        A = -f * 2 * mu * np.diag([1.0, 0.0, 0.0])
        m = tangent_margin(RbfParams(C, np.zeros((3, 3)), A, epsilon=0.01), mat, mu, lam, probes)
        assert np.sign(m) == sign, (f, m)
    # Inside the data (the centres' box) the data decide: no probe there, no verdict.
    inside = 1 + 0.001 * rng.standard_normal((50, 3))
    assert tangent_margin(RbfParams(C, np.zeros((3, 3)), -10 * M * np.eye(3), epsilon=0.01),
                          mat, mu, lam, inside) == np.inf


def test_projected_linear_part_is_the_nearest_stable_one():
    from matlearn.learning.fit import project_linear_part, tangent_margin

    mat = Material("corotated", 3e5, 0.3, 1000.0)
    nominal = _scene(mat).model()
    mu, lam = float(nominal.mu[0]), float(nominal.lam[0])
    C = 1 + 0.01 * np.eye(3)
    probes = 1 + 0.1 * np.random.default_rng(0).standard_normal((200, 3))
    rng = np.random.default_rng(1)
    A = -3 * mu * np.diag([1.0, 0.2, 0.0]) + 0.2 * mu * rng.standard_normal((3, 3))
    p = RbfParams(C, np.zeros((3, 3)), A, epsilon=0.01)
    q = project_linear_part(p, mat, mu, lam)
    assert tangent_margin(p, mat, mu, lam, probes) < 0 <= tangent_margin(q, mat, mu, lam, probes)
    # Only the symmetric part moves, by the negative eigen-part of the total tangent at rest.
    T0 = 2 * mu * np.eye(3) + lam * np.ones((3, 3))
    w = np.linalg.eigvalsh(0.5 * (T0 + A + (T0 + A).T))
    D = q.linear - A
    np.testing.assert_allclose(D, D.T, atol=1e-9 * mu)
    assert np.linalg.norm(D) == pytest.approx(np.linalg.norm(np.minimum(w, 0)), rel=1e-3)
    # A stable linear part is left alone (up to the round-off floor).
    ok = project_linear_part(RbfParams(C, np.zeros((3, 3)), -0.5 * mu * np.eye(3), epsilon=0.01), mat, mu, lam)
    np.testing.assert_allclose(ok.linear, -0.5 * mu * np.eye(3), atol=1e-9)


def _softer_truth_forces(steps=90):
    """A co-rotated bar whose truth is 1/3 softer than its nominal model: the scene, both
    models, the truth's motion (X, Vel) and the exact force difference truth - nominal per frame."""
    sc = _scene(Material("corotated", 3e5, 0.3, 1000.0))
    nominal = sc.model()
    truth = _scene(Material("corotated", 2e5, 0.3, 1000.0)).model()
    X, Vel = _frames(sc, truth, steps=steps)
    fc = np.stack([np.asarray(truth.forces(x, v)) - np.asarray(nominal.forces(x, v)) for x, v in zip(X, Vel)])
    return sc, nominal, truth, X, Vel, fc


def test_linear_part_penalty_shrinks_the_global_modulus_change_and_is_off_at_zero():
    # Exact forces of a 1/3 softer co-rotated truth: the free fit puts the change in the linear
    # part A (a global modulus change); the linear penalty (fit.solve_fit `linear`, the tangent
    # penalty applied to A) shrinks A monotonically towards 0, and weight 0 is the free fit.
    from matlearn.learning.fit import fit_system, solve_fit

    sc, nominal, truth, X, Vel, fc = _softer_truth_forces()
    system = fit_system(nominal, [FitFrames(X, Vel, fc, None, sc.fixed)], num_centers=12, damping=False)
    M = system.modulus
    norms = []
    for w in (0.0, 0.1, 1.0, 1e6):
        p, info = solve_fit(system, 1e-8, 1.0, w)
        assert info["linear"] == w
        norms.append(np.linalg.norm(p.linear) / M)
    free, _ = solve_fit(system, 1e-8, 1.0)
    assert np.array_equal(free.linear, solve_fit(system, 1e-8, 1.0, 0.0)[0].linear)
    # the free fit finds the modulus change: the truth's tangent at rest minus the nominal's is
    # -(1/3) of it, Frobenius norm ~0.4 M
    mu_n, lam_n, mu_t, lam_t = nominal.mu[0], nominal.lam[0], truth.mu[0], truth.lam[0]
    dT = 2 * (mu_t - mu_n) * np.eye(3) + (lam_t - lam_n) * np.ones((3, 3))
    assert np.linalg.norm(free.linear - dT) < 0.15 * np.linalg.norm(dT)
    assert norms[0] > norms[1] > norms[2] > norms[3]
    assert norms[3] < 1e-3 * norms[0]


def test_edge_penalty_flattens_the_rbf_slope_where_the_correction_is_extended():
    # Noisy forces of a softer truth (as above): the unpenalised RBF part has a sizeable slope
    # where a motion twice the fitted one leaves the centres' box, and the C1 extension carries
    # that slope on without end. The edge penalty (fit.solve_fit `edge`) takes it down there
    # while the fit inside the data barely changes.
    from matlearn.learning.fit import fit_system, kernel_gradients, solve_fit

    sc, nominal, truth, X, Vel, fc = _softer_truth_forces()
    fc = fc + 0.2 * np.sqrt(np.mean(fc**2)) * np.random.default_rng(1).standard_normal(fc.shape)
    system = fit_system(nominal, [FitFrames(X, Vel, fc, None, sc.fixed)], num_centers=16, damping=False)
    S = 1 + 2 * (system.samples - 1)
    out = np.any((S < system.box[0]) | (S > system.box[1]), axis=1)
    assert out.mean() > 0.05
    edge_pts = np.clip(S[out], *system.box)

    def edge_slope(p):
        J = np.einsum("kc,ikb->icb", p.weights, kernel_gradients(edge_pts, p.centers, p.epsilon, p.box()))
        return float(np.sqrt(np.mean(np.sum(J**2, axis=(1, 2))))) / system.modulus

    free, i0 = solve_fit(system, 1e-10, 1e-3)
    flat, i1 = solve_fit(system, 1e-10, 1e-3, edge=100.0)
    assert i1["edge"] == 100.0
    assert edge_slope(free) > 0.02
    assert edge_slope(flat) < 0.2 * edge_slope(free), (edge_slope(flat), edge_slope(free))
    # Measured: edge slope 0.30 -> 0.003 of the modulus, residual ratio 0.873 -> 0.877.
    assert i1["residual_ratio"] < 1.1 * i0["residual_ratio"]
    np.testing.assert_allclose(system.edge_penalty(), system.edge_penalty().T)
