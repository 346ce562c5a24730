"""static_solve with no load at all (zero gravity, no external force) — a scene with gravity
[0, 0, 0] is valid, and the held pose of a recording's first frame is such a solve (prescribed
marker vertices): its residual was measured against 1e-12 N, so it always "did not converge"."""
from __future__ import annotations

import numpy as np

from matlearn import _core, meshes
from matlearn.materials import Damping, Material, make_model


def _bar():
    V, T = meshes.grid_tets((8, 2, 2), (0.16, 0.03, 0.03), (0, -0.015, -0.015))
    mesh = meshes.TetMesh(V, T)
    model = make_model(mesh, Material("corotated", 4e5, 0.4, 1000.0), Damping())
    fixed = np.flatnonzero(V[:, 0] < 1e-9)
    tip = np.flatnonzero(V[:, 0] > 0.16 - 1e-9)
    return V, model, fixed, tip


def test_pose_held_by_prescribed_vertices_without_gravity():
    V, model, fixed, tip = _bar()
    x = V.copy()
    x[tip, 1] += 0.005
    integ = _core.time.Integrator(model, fixed, 1e-3, np.zeros(3))
    integ.set_prescribed(tip)
    integ.set_state(x, np.zeros_like(V))
    integ.static_solve(np.zeros_like(V), load_steps=1)
    X = np.asarray(integ.x)
    f = model.forces(X, np.zeros_like(V))
    free = np.setdiff1d(np.arange(len(V)), np.r_[fixed, tip])
    # equilibrium of the free vertices, far below the reactions at the held tip
    assert np.abs(f[free]).max() < 1e-8 * np.abs(f[tip]).max()
    np.testing.assert_allclose(X[tip], x[tip])
    # the same pose as with a negligible gravity (which the old reference scale accepted)
    g = _core.time.Integrator(model, fixed, 1e-3, np.array([0.0, -1e-9, 0.0]))
    g.set_prescribed(tip)
    g.set_state(x, np.zeros_like(V))
    g.static_solve(np.zeros_like(V), load_steps=1)
    np.testing.assert_allclose(X, np.asarray(g.x), atol=1e-9)


def test_rest_without_any_load_stays_at_rest():
    V, model, fixed, _ = _bar()
    integ = _core.time.Integrator(model, fixed, 1e-3, np.zeros(3))
    integ.set_state(V.copy(), np.zeros_like(V))
    integ.static_solve(np.zeros_like(V), load_steps=2)
    np.testing.assert_allclose(np.asarray(integ.x), V, atol=1e-12)
