"""A clamped cantilever against Euler-Bernoulli beam theory: static tip deflection under a small
tip load and under gravity, and the first bending frequency of a released small vibration,
each within 5 % on the finest mesh, with the error decreasing under mesh refinement.

Linear tets lock in bending: the error is set by the number of elements through the height
(here 2, 4, 8 layers; 8 gives ~4 % too stiff). Poisson ratio 0 so that EB's uniaxial
assumption holds at the clamp (no anticlastic stiffening); L/h = 10 keeps shear deformation
(Timoshenko correction +0.6 %) well below the tolerance.
"""
import numpy as np
import pytest

from matlearn import _core, meshes
from matlearn.materials import Material, make_model

L, B, HH = 0.5, 0.05, 0.05  # length, width, height (m)
E, NU, RHO = 1e6, 0.0, 1000.0
I_AREA = B * HH**3 / 12
MESHES = [(20, 1, 2), (40, 1, 4), (80, 1, 8)]  # the last has 3840 tets


def setup(cells):
    mesh = meshes.bar(L, B, HH, cells)
    model = make_model(mesh, Material("corotated", E, NU, RHO))
    X = mesh.vertices
    fixed = np.where(X[:, 0] < 1e-9)[0]
    tip = np.where(X[:, 0] > L - 1e-9)[0]
    return mesh, model, fixed, tip


def tip_deflection(cells, load):
    mesh, model, fixed, tip = setup(cells)
    X = mesh.vertices
    f = np.zeros_like(X)
    if load == "tip":
        P = 5e-3  # N: tip deflection ~ 1e-3 L, linear regime
        f[tip, 2] = -P / len(tip)
        expected = P * L**3 / (3 * E * I_AREA)
        g = np.zeros(3)
    else:
        g = np.array([0.0, 0.0, -0.02])  # a small "gravity": q = rho A g
        expected = RHO * B * HH * 0.02 * L**4 / (8 * E * I_AREA)
    integ = _core.time.Integrator(model, fixed, 1e-3, g)
    integ.static_solve(f)
    return -(integ.x[tip, 2] - X[tip, 2]).mean(), expected


@pytest.mark.parametrize("load", ["tip", "gravity"])
def test_static_tip_deflection_converges_to_euler_bernoulli(load):
    errors = []
    for cells in MESHES:
        d, expected = tip_deflection(cells, load)
        errors.append(abs(d - expected) / expected)
    print(f"{load}: relative errors {errors}")
    assert errors[-1] < 0.05, errors
    assert errors[0] > errors[1] > errors[2], f"no refinement trend: {errors}"


def first_frequency(cells):
    """Release from a static tip deflection, no damping, no gravity; period from the zero
    crossings of the tip displacement."""
    mesh, model, fixed, tip = setup(cells)
    X = mesh.vertices
    omega = 1.8751**2 * np.sqrt(E * I_AREA / (RHO * B * HH * L**4))
    period = 2 * np.pi / omega
    h = period / 200  # BE frequency error ~ (omega h)^2 / 3 < 1e-3
    integ = _core.time.Integrator(model, fixed, h, np.zeros(3))
    f = np.zeros_like(X)
    f[tip, 2] = -5e-3 / len(tip)
    integ.static_solve(f)
    steps = int(1.35 * period / h)
    Xs, _ = integ.simulate(steps, np.zeros_like(X))
    z = (Xs[:, tip, 2] - X[tip, 2]).mean(axis=1)
    t = np.arange(len(z)) * h
    i = np.where(np.sign(z[:-1]) != np.sign(z[1:]))[0]
    crossings = t[i] - z[i] * h / (z[i + 1] - z[i])  # linear interpolation
    assert len(crossings) >= 3, f"expected >= 3 zero crossings, got {len(crossings)}"
    T = crossings[2] - crossings[0]
    return 2 * np.pi / T, omega


def test_first_bending_frequency_converges_to_euler_bernoulli():
    errors = []
    for cells in MESHES:
        w, expected = first_frequency(cells)
        errors.append(abs(w - expected) / expected)
    print(f"frequency: relative errors {errors}")
    assert errors[-1] < 0.05, errors
    assert errors[0] > errors[1] > errors[2], f"no refinement trend: {errors}"
