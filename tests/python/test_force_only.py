"""The force-only correction path (Correction.evaluate_values, used by every Model evaluation that
needs no tangent: residuals of the space-time problem, chord steps of the time step) gives
bitwise the values of the full evaluate, inside and outside the RBF's box, with and without its
damping part, and for the MLP (fixed-size 6-H-H-3|4 paths, rate-dependent or not, and the generic
loop); and a Model's stress and damping through that path equal the full path's."""
import numpy as np
import pytest

from matlearn import _core, materials, meshes


def _rbf(box: bool, damping: bool, seed=0):
    rng = np.random.default_rng(seed)
    c = 1.0 + 0.2 * rng.standard_normal((7, 3))
    w = 1e4 * rng.standard_normal((7, 3))
    A = 1e4 * rng.standard_normal((3, 3))
    b = 1e3 * rng.standard_normal(3)
    wa = 1e-3 * rng.standard_normal(7) if damping else np.zeros(0)
    lo, hi = (np.array([0.9, 0.92, 0.88]), np.array([1.1, 1.05, 1.12])) if box else (None, None)
    return _core.correction.RbfCorrection(c, w, A, b, wa, 2e-3 if damping else 0.0, 0.05,
                                          lower=lo, upper=hi)


@pytest.mark.parametrize("box", [False, True])
@pytest.mark.parametrize("damping", [False, True])
def test_rbf_values_bitwise_equal_full_evaluate(box, damping):
    rng = np.random.default_rng(1)
    Fh = 1.0 + 0.15 * rng.standard_normal((500, 3))  # about half of the rows outside the box
    Fh[:50] = [1.0, 1.0, 1.0]
    Fhd = rng.standard_normal((500, 3))
    c = _rbf(box, damping)
    dPh, _, _, dalpha = c.evaluate(Fh, Fhd)
    v_dPh, v_dalpha = c.evaluate_values(Fh, Fhd)
    assert np.abs(dPh).max() > 1e3  # a real correction
    np.testing.assert_array_equal(v_dPh, dPh)
    np.testing.assert_array_equal(v_dalpha, dalpha)


def _mlp(hidden, outputs: int, rate: bool, seed=0):
    rng = np.random.default_rng(seed)
    widths = [6, *hidden, outputs]
    layers = []
    for a, b in zip(widths[:-1], widths[1:]):
        W = rng.standard_normal((b, a)) / np.sqrt(a)
        if a == 6 and not rate:
            W[:, 3:] = 0.0  # rate-independent net: its d_dFhdot is exactly 0
        layers.append((W, 0.3 * rng.standard_normal(b)))
    return _core.correction.MlpCorrection(layers, 1.0 + 0.01 * rng.standard_normal(6),
                                          0.1 + rng.random(6), 1e3 * rng.standard_normal(outputs),
                                          1e4 * (0.5 + rng.random(outputs)))


@pytest.mark.parametrize("hidden,outputs,rate", [((6, 6), 4, False), ((6, 6), 3, True),
                                                  ((16, 16), 4, True), ((16, 16), 3, False),
                                                  ((8, 5, 7), 4, True)])
def test_mlp_values_bitwise_equal_full_evaluate(hidden, outputs, rate):
    rng = np.random.default_rng(3)
    Fh = 1.0 + 0.15 * rng.standard_normal((500, 3))
    Fhd = rng.standard_normal((500, 3))
    c = _mlp(hidden, outputs, rate)
    dPh, J, Jd, dalpha = c.evaluate(Fh, Fhd)
    v_dPh, v_dalpha = c.evaluate_values(Fh, Fhd)
    assert np.abs(dPh).max() > 1e3 and np.abs(J).max() > 1e3  # a real correction
    assert (np.abs(Jd).max() > 0) == rate
    np.testing.assert_array_equal(v_dPh, dPh)
    np.testing.assert_array_equal(v_dalpha, dalpha)
    if outputs == 3:
        np.testing.assert_array_equal(v_dalpha, 0.0)


@pytest.mark.parametrize("kind", ["rbf", "mlp"])
def test_model_force_only_path_equals_full_path(kind):
    # principal_kinematics evaluates without tangents (the values path); element_state with K and
    # D (the full evaluate). The total stress and damping coefficient they see must be identical.
    mesh = meshes.bar(0.1, 0.02, 0.02, cells=(6, 2, 2))
    model = materials.make_model(mesh, materials.Material("neo_hookean", 2e5, 0.4, 1000.0),
                                 materials.Damping(0.0, 0.005))
    model.correction = _rbf(True, True) if kind == "rbf" else _mlp((6, 6), 4, True)
    rng = np.random.default_rng(2)
    V = np.asarray(mesh.vertices)
    x = V + 0.004 * rng.standard_normal(V.shape)
    v = 0.1 * rng.standard_normal(V.shape)
    _, _, Ph, aK = model.principal_kinematics(x, v)
    st = model.element_state(x, v, True)
    assert np.abs(st["dPh_correction"]).max() > 1e3
    np.testing.assert_array_equal(Ph, st["Ph"])
    np.testing.assert_array_equal(aK, st["alpha_K"])
