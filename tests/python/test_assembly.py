"""Assembled operators through the bindings: directional finite differences of the internal
force against the stiffness K = -df/dx and of the damping force against D = -df/dv, with and
without learned corrections (Python callback, RBF, MLP), whose own Jacobians are checked
against finite differences of `.evaluate`; K symmetric, rigid null space, mass sums, B map."""
import numpy as np
import pytest

from matlearn import _core, meshes
from matlearn.materials import Damping, Material, make_model

corr = _core.correction
L, W_, RHO = 0.2, 0.04, 1100.0


def small_bar():
    return meshes.bar(L, W_, W_, cells=(4, 2, 2))


def deformed(mesh, seed=0, amp=0.05):
    rng = np.random.default_rng(seed)
    X = mesh.vertices
    x = X.copy()
    t = X[:, 0] / L
    x[:, 0] *= 1.1
    x[:, 2] += 0.3 * L * t**2
    return x + amp * W_ * rng.uniform(-1, 1, X.shape)


def python_correction():
    """A smooth nonlinear correction with exact Jacobians; symmetric rate Jacobian."""
    C = np.array([[3e3, 1e3, -5e2], [1e3, 2e3, 0.0], [-5e2, 0.0, 4e3]])

    def fn(Fh, Fhdot):
        e = Fh - 1.0
        dPh = (e**2) @ C.T + 50.0 * Fhdot
        J = 2.0 * C[None, :, :] * e[:, None, :]
        Jd = np.broadcast_to(50.0 * np.eye(3), (len(Fh), 3, 3)).copy()
        return dPh, J, Jd, np.full(len(Fh), 1e-3)

    return corr.PythonCorrection(fn)


def rbf_correction(seed=1):
    rng = np.random.default_rng(seed)
    c = 1.0 + 0.2 * rng.standard_normal((6, 3))
    return corr.RbfCorrection(c, 2e3 * rng.standard_normal((6, 3)), 1e3 * rng.standard_normal((3, 3)),
                              np.zeros(3), 1e-3 * np.abs(rng.standard_normal(6)), 0.0, 0.05)


def mlp_correction(seed=2):
    rng = np.random.default_rng(seed)
    sizes = [6, 6, 6, 3]
    layers = [(0.7 * rng.standard_normal((o, i)), 0.1 * rng.standard_normal(o)) for i, o in zip(sizes[:-1], sizes[1:])]
    return corr.MlpCorrection(layers, np.r_[np.ones(3), np.zeros(3)], np.r_[0.1 * np.ones(3), np.ones(3)],
                              np.zeros(3), 1e3 * np.ones(3))


CORRECTIONS = {"none": None, "python": python_correction, "rbf": rbf_correction, "mlp": mlp_correction}


def model_for(material, correction=None, damping=None):
    mesh = small_bar()
    edits = [(2e4, 1.25, 0.2), (-1e4, 0.75, 0.2)] if material == "designed" else []
    return make_model(mesh, Material(material, 1e5, 0.4, RHO, edits), damping,
                      None if CORRECTIONS.get(correction) is None else CORRECTIONS[correction]())


@pytest.mark.parametrize("material", ["corotated", "neo_hookean", "stvk", "designed"])
def test_force_derivative_is_minus_stiffness(material):
    model = model_for(material)
    x = deformed(model.mesh)
    v = np.zeros_like(x)
    K = model.stiffness(x, v, project_psd=False)
    np.testing.assert_allclose((K - K.T).toarray(), 0.0, atol=1e-10 * abs(K).max())
    rng = np.random.default_rng(3)
    for _ in range(3):
        d = rng.standard_normal(x.shape)
        h = 1e-7
        fd = (model.forces(x + h * d, v) - model.forces(x - h * d, v)).ravel() / (2 * h)
        Kd = -(K @ d.ravel())
        np.testing.assert_allclose(fd, Kd, rtol=0, atol=1e-5 * np.abs(Kd).max())


@pytest.mark.parametrize("name", ["python", "rbf", "mlp"])
def test_force_derivative_with_correction(name):
    model = model_for("corotated", name)
    x = deformed(model.mesh, seed=5)
    v = np.zeros_like(x)
    K = model.stiffness(x, v, project_psd=False)
    d = np.random.default_rng(4).standard_normal(x.shape)
    h = 1e-7
    fd = (model.forces(x + h * d, v) - model.forces(x - h * d, v)).ravel() / (2 * h)
    Kd = -(K @ d.ravel())
    np.testing.assert_allclose(fd, Kd, rtol=0, atol=1e-5 * np.abs(Kd).max())
    # The correction really changes the force (the test would catch a dropped Jacobian).
    f0 = make_model(model.mesh, Material("corotated", 1e5, 0.4, RHO)).forces(x, v)
    assert np.abs(model.forces(x, v) - f0).max() > 1e-3 * np.abs(f0).max()


@pytest.mark.parametrize("name", ["none", "python"])
def test_damping_matrix_is_velocity_derivative(name):
    model = model_for("neo_hookean", name, Damping(alpha_mass=0.7, alpha_stiffness=0.02))
    x = deformed(model.mesh, seed=6, amp=0.03)
    rng = np.random.default_rng(7)
    v = 0.1 * rng.standard_normal(x.shape)
    dv = rng.standard_normal(x.shape)
    D = model.damping_matrix(x, v)
    h = 1e-4  # the force is linear in v here
    fd = (model.forces(x, v + h * dv) - model.forces(x, v - h * dv)).ravel() / (2 * h)
    Dd = -(D @ dv.ravel())
    np.testing.assert_allclose(fd, Dd, rtol=0, atol=1e-7 * np.abs(Dd).max())


@pytest.mark.parametrize("name", ["rbf", "mlp", "python"])
def test_correction_jacobians_match_finite_differences(name):
    c = CORRECTIONS[name]()
    rng = np.random.default_rng(8)
    Fh = 1.0 + 0.15 * rng.standard_normal((12, 3))
    Fhdot = 0.5 * rng.standard_normal((12, 3))
    _, J, Jd, _ = c.evaluate(Fh, Fhdot)
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd = (c.evaluate(Fh + d, Fhdot)[0] - c.evaluate(Fh - d, Fhdot)[0]) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
        fdd = (c.evaluate(Fh, Fhdot + d)[0] - c.evaluate(Fh, Fhdot - d)[0]) / (2 * h)
        np.testing.assert_allclose(Jd[:, :, k], fdd, rtol=1e-5, atol=1e-6 * max(np.abs(fdd).max(), 1.0))


@pytest.mark.parametrize("material", ["corotated", "neo_hookean", "stvk"])
def test_rigid_motions_in_null_space_at_rest(material):
    model = model_for(material)
    X = model.mesh.vertices
    v = np.zeros_like(X)
    np.testing.assert_allclose(model.forces(X, v), 0.0, atol=1e-9)
    for psd in (False, True):
        K = model.stiffness(X, v, project_psd=psd)
        modes = [np.tile(np.eye(3)[k], (len(X), 1)) for k in range(3)]
        modes += [np.cross(np.eye(3)[k], X) for k in range(3)]
        for r in modes:
            assert np.abs(K @ r.ravel()).max() <= 1e-9 * abs(K).max()


def test_mass_sums_and_force_map():
    model = model_for("stvk")
    mesh = model.mesh
    np.testing.assert_allclose(mesh.rest_volumes.sum(), L * W_ * W_, rtol=1e-12)
    np.testing.assert_allclose(model.vertex_mass.sum(), RHO * L * W_ * W_, rtol=1e-12)
    x = deformed(mesh, seed=9)
    v = np.zeros_like(x)
    B = model.force_map(x)
    assert B.shape == (3 * mesh.num_vertices, 3 * mesh.num_tets)
    _, _, Ph, _ = model.principal_kinematics(x, v)
    np.testing.assert_allclose(B @ Ph.ravel(), model.forces(x, v).ravel(), atol=1e-9 * np.abs(B @ Ph.ravel()).max())


def test_stiffness_damping_map_columns():
    model = model_for("corotated", damping=Damping(alpha_stiffness=0.01))
    x = deformed(model.mesh, seed=10, amp=0.02)
    v = 0.1 * np.random.default_rng(11).standard_normal(x.shape)
    G = model.stiffness_damping_map(x, v)
    st = model.element_state(x, v, True)
    # Sum over columns weighted by alpha_K gives the stiffness-damping force -alpha_K K v.
    f_damp = model.forces(x, v) - model_for("corotated").forces(x, v)
    np.testing.assert_allclose(G @ st["alpha_K"], f_damp.ravel(), atol=1e-9 * np.abs(f_damp).max())
