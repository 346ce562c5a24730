"""Shared learning test helpers: the small learning case of the loop and end-to-end tests (a
neo-Hookean bar learned from a co-rotated nominal model: release from a tip load; the test pulls
harder) and the nominal energy used by the passivity tests."""
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
