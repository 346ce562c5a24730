"""Materials through the Python bindings: zero stress at rest, stress = dEnergy/ds and tangent
= dStress/ds by central differences on seeded random, near-repeated and inverted stretches,
and the Material description's validation."""
import numpy as np
import pytest

from matlearn import _core
from matlearn.materials import Material

fem = _core.fem
MU, LAM = 3.0e4, 1.2e5
EDITS = [(2.0e4, 1.3, 0.2), (-1.5e4, 0.7, 0.2)]
CASES = [("corotated", []), ("neo_hookean", []), ("stvk", []), ("designed", EDITS)]


def states():
    rng = np.random.default_rng(0)
    S = -np.sort(-rng.uniform(0.6, 1.5, (10, 3)), axis=1)
    extra = [
        (1.2, 1.2 + 1e-9, 0.9),  # near-repeated
        (1.25, 1.25, 1.25),  # repeated, inside the tension edit
        (1.35, 0.72, 0.72 - 1e-9),
        (1.1, 0.9, -0.3),  # inverted
        (1.2, 0.7, -0.05),
    ]
    return np.vstack([S, extra])


def call(fn, model, edits, S):
    k = len(S)
    return fn(model, S, np.full(k, MU), np.full(k, LAM), edits)


def assert_close_rel(a, b, tol, what):
    a, b = np.asarray(a), np.asarray(b)
    scale = np.maximum(1.0, np.maximum(np.abs(a), np.abs(b)))
    bad = np.abs(a - b) > tol * scale
    assert not bad.any(), f"{what}: {a[bad][:5]} vs {b[bad][:5]}"


@pytest.mark.parametrize("model,edits", CASES, ids=[c[0] for c in CASES])
def test_zero_stress_at_rest(model, edits):
    one = np.ones((1, 3))
    np.testing.assert_allclose(call(fem.principal_stress, model, edits, one), 0.0, atol=1e-9)
    np.testing.assert_allclose(call(fem.principal_energy, model, edits, one), 0.0, atol=1e-9)
    H = call(fem.principal_stress_derivative, model, edits, one)[0]
    np.testing.assert_allclose(H, 2 * MU * np.eye(3) + LAM, rtol=1e-9)


@pytest.mark.parametrize("model,edits", CASES, ids=[c[0] for c in CASES])
def test_stress_is_energy_gradient(model, edits):
    S, h = states(), 1e-6
    P = call(fem.principal_stress, model, edits, S)
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        fd = (call(fem.principal_energy, model, edits, S + d) - call(fem.principal_energy, model, edits, S - d)) / (2 * h)
        assert_close_rel(P[:, i], fd, 1e-4, f"{model} dpsi/ds{i}")


@pytest.mark.parametrize("model,edits", CASES, ids=[c[0] for c in CASES])
def test_tangent_is_stress_gradient(model, edits):
    S, h = states(), 1e-6
    H = call(fem.principal_stress_derivative, model, edits, S)
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        fd = (call(fem.principal_stress, model, edits, S + d) - call(fem.principal_stress, model, edits, S - d)) / (2 * h)
        assert_close_rel(H[:, :, j], fd, 1e-4, f"{model} dP/ds{j}")


def test_stretch_edits_only_act_in_their_range():
    S = np.array([[1.0, 1.0, 1.0], [1.05, 1.0, 0.95], [1.3, 1.0, 1.0], [0.7, 1.0, 1.0]])
    base = call(fem.principal_stress, "neo_hookean", [], S)
    edited = call(fem.principal_stress, "designed", EDITS, S)
    np.testing.assert_allclose(edited[:2], base[:2], rtol=1e-12, atol=1e-9)  # outside the bumps
    np.testing.assert_allclose(edited[2, 0] - base[2, 0], 2.0e4, rtol=1e-12)  # tension bump peak
    np.testing.assert_allclose(edited[3, 0] - base[3, 0], -1.5e4, rtol=1e-12)  # compression


def test_rotation_variant_svd_of_inverted_matrix():
    F = np.diag([1.1, 0.9, -0.3])
    U, s, V = fem.rotation_variant_svd(F)
    np.testing.assert_allclose(np.linalg.det(U), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(V), 1.0, atol=1e-12)
    np.testing.assert_allclose(U @ np.diag(s) @ V.T, F, atol=1e-12)
    assert s[2] < 0


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(model="rubber"), "unknown material model"),
        (dict(poisson_ratio=0.5), "poisson_ratio"),
        (dict(poisson_ratio=-0.1), "poisson_ratio"),
        (dict(youngs_modulus=0.0), "youngs_modulus"),
        (dict(density=-1.0), "density"),
    ],
)
def test_material_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Material(**kwargs)


def test_edit_covering_rest_is_rejected():
    from matlearn import meshes
    from matlearn.materials import make_model

    mesh = meshes.bar(cells=(2, 1, 1))
    with pytest.raises(ValueError, match="rest stretch"):
        make_model(mesh, Material("designed", edits=[(1e4, 1.1, 0.2)]))
