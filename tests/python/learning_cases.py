"""Shared learning test helpers: the small learning case of the loop and end-to-end tests (a
neo-Hookean bar learned from a co-rotated nominal model: release from a tip load; the test pulls
harder), a slowly driven bar (its stress scale free) and the nominal energy used by the passivity
tests."""
from __future__ import annotations

import numpy as np

from matlearn import _core, meshes
from matlearn.materials import Damping, Material
from matlearn.synthetic import Motion, make_case

L = 0.08  # bar length (m)


def small_bar_case(folder):
    mesh = meshes.bar(L, 0.02, 0.02, cells=(5, 1, 1))
    tip = [[L - 0.011, -1, -1], [1, 1, 1]]
    motions = [Motion("release", "train", 0.1, load={"box": tip, "force": [0, 0.25, 0.08]}),
               Motion("release", "test", 0.1, load={"box": tip, "force": [0, 0.4, -0.05]})]
    return make_case(folder, "bar", mesh,
                     Material("neo_hookean", 2e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     mesh, Material("corotated", 3.5e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     [[-1, -1, -1], [1e-4, 1, 1]], motions, marker_fraction=0.5, seed=3)


def driven_bar(folder, gravity=(0.0, 0.0, 0.0), release_first: bool = False):
    """A bar clamped at one end whose other end is moved slowly up and down (keyframes, 0.3 s,
    well below its first frequency): near equilibrium between clamp and drive at any stiffness.
    release_first: a first train recording releases the bar from a tip load (small_bar_case's),
    which does fix the stiffness."""
    mesh = meshes.bar(L, 0.02, 0.02, cells=(5, 1, 1))
    tip = [[L - 0.011, -1, -1], [1, 1, 1]]
    kf = [[0.0, [0, 0, 0]], [0.1, [0, 0.006, 0]], [0.2, [0, -0.006, 0]], [0.3, [0, 0, 0]]]
    motions = [Motion("drive", "train", 0.3, drive={"box": tip, "keyframes": kf}),
               Motion("drive", "test", 0.3, drive={"box": tip, "keyframes": [[t, [0, 0, 1.5 * d[1]]]
                                                                            for t, d in kf]})]
    if release_first:
        motions.insert(0, Motion("release", "train", 0.1, load={"box": tip, "force": [0, 0.25, 0.08]}))
    return make_case(folder, "driven", mesh, Material("neo_hookean", 2e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     mesh, Material("corotated", 3.5e5, 0.43, 1000.0), Damping(0.0, 0.004),
                     [[-1, -1, -1], [1e-4, 1, 1]], motions, marker_fraction=0.5, seed=3, gravity=list(gravity))


def released_from_bent_pose(sc, model, steps: int = 200):
    """(X, Vel) (steps+1, #V, 3) of the cantilever of scene `sc` (length L) released from a bent
    pose at rest, unforced, undriven and without gravity."""
    n = sc.mesh.num_vertices
    V = np.asarray(sc.mesh.vertices)
    x0 = V.copy()
    x0[:, 1] += 0.05 * (V[:, 0] / L) ** 2  # bent initial pose, at rest
    x0[sc.fixed] = V[sc.fixed]
    integ = _core.time.Integrator(model, sc.fixed, 1e-3, np.zeros(3), 30, 1e-12)
    integ.set_state(x0, np.zeros((n, 3)))
    return integ.simulate(steps, np.zeros((n, 3)), 1)


def assert_energy_decays_from_a_bent_pose(sc, model, energy_scene, steps: int = 200):
    """After :func:`released_from_bent_pose`, the energy (`nominal_energy` with `energy_scene`'s
    law) never increases and decays by at least 10 %."""
    X, Vel = released_from_bent_pose(sc, model, steps)
    E = np.array([nominal_energy(energy_scene, model, x, v) for x, v in zip(X, Vel)])
    assert E[0] > 0
    assert np.all(np.diff(E) <= 1e-9 * E[0]), np.diff(E).max()
    assert E[-1] < 0.9 * E[0]


def nominal_energy(sc, model, x, v) -> float:
    """Nominal elastic energy + kinetic energy (J) of state (x, v) of scene `sc` under `model`."""
    mu, lam = sc.material.lame(sc.mesh.num_tets)
    Fh = np.asarray(model.principal_kinematics(x, v)[0])
    psi = np.asarray(_core.fem.principal_energy(sc.material.model, Fh, mu, lam, []))
    m = np.asarray(model.vertex_mass)
    return float(psi @ np.asarray(sc.mesh.rest_volumes) + 0.5 * (m * (v**2).sum(1)).sum())


def scaled_fit(factor):
    """A stand-in for learning.loop.solve_fit that returns the real fit scaled by `factor`
    (elastic and damping parts): a wrong-way (< 0) or overshooting (> 1) update for loop tests;
    install it with monkeypatch.setattr(loop, "solve_fit", scaled_fit(f))."""
    from matlearn.learning import loop

    real = loop.solve_fit

    def fit(*args, **kw):
        p, info = real(*args, **kw)
        p.weights, p.linear, p.bias = factor * p.weights, factor * p.linear, factor * p.bias
        p.alpha_weights, p.alpha_bias = factor * p.alpha_weights, factor * p.alpha_bias
        return p, info
    return fit
