"""Small-strain statics against an independent library: scikit-fem's linear elasticity
(ElementVectorH1(ElementTetP1)) on exactly our tet mesh, under a small tip load plus body
force, must agree with our nonlinear static solve (every law linearises to the same Hooke's
law at rest) to ~1e-3 relative."""
import numpy as np
import pytest

skfem = pytest.importorskip("skfem")
from skfem.models.elasticity import linear_elasticity  # noqa: E402

from matlearn import _core, meshes  # noqa: E402
from matlearn.materials import Material, make_model  # noqa: E402

L, W_ = 0.2, 0.04
E, NU, RHO = 1e5, 0.3, 1000.0
G = np.array([0.0, 0.003, -0.005])  # small body force per mass (m/s^2)


def irregular_bar():
    """A bar with jittered interior vertices, so the tets are not all congruent."""
    mesh = meshes.bar(L, W_, W_, cells=(8, 2, 2))
    V = mesh.vertices.copy()
    rng = np.random.default_rng(0)
    interior = (V[:, 0] > 1e-9) & (V[:, 0] < L - 1e-9)
    V[interior] += 0.15 * (L / 8) * rng.uniform(-1, 1, (interior.sum(), 3)) * [1, 0, 0]
    return meshes.TetMesh(V, mesh.tets)


def skfem_displacement(mesh, f_nodal, fixed):
    m = skfem.MeshTet(np.ascontiguousarray(mesh.vertices.T), np.ascontiguousarray(mesh.tets.T))
    basis = skfem.Basis(m, skfem.ElementVectorH1(skfem.ElementTetP1()))
    lam = E * NU / ((1 + NU) * (1 - 2 * NU))
    mu = E / (2 * (1 + NU))
    K = skfem.asm(linear_elasticity(lam, mu), basis)
    nd = basis.nodal_dofs  # (3, #V): dof of component k at vertex i
    f = np.zeros(basis.N)
    f[nd.T.ravel()] = f_nodal.ravel()
    D = nd[:, fixed].ravel()
    u = skfem.solve(*skfem.condense(K, f, D=D))
    return u[nd.T]  # (#V, 3)


@pytest.mark.parametrize("material", ["corotated", "neo_hookean", "stvk"])
def test_small_strain_statics_match_scikit_fem(material):
    mesh = irregular_bar()
    X = mesh.vertices
    model = make_model(mesh, Material(material, E, NU, RHO))
    fixed = np.where(X[:, 0] < 1e-9)[0]
    tip = np.where(X[:, 0] > L - 1e-9)[0]
    f = np.zeros_like(X)
    f[tip] = np.array([1e-5, 5e-6, -2e-5]) / len(tip)  # N
    integ = _core.time.Integrator(model, fixed, 1e-3, G)
    integ.static_solve(f)
    u = integ.x - X
    # Same load for scikit-fem: point loads + lumped body force (our mass is lumped; for a
    # constant body force lumping is exact on linear tets).
    f_total = f + model.vertex_mass[:, None] * G
    u_ref = skfem_displacement(mesh, f_total, fixed)
    scale = np.abs(u_ref).max()
    assert 1e-6 * L < scale < 1e-3 * L  # small strain, but not nothing
    np.testing.assert_allclose(u, u_ref, rtol=0, atol=1e-3 * scale)
