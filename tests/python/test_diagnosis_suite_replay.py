"""_core.time.LinearisedReplay (the diagnosis's fast replay: PCG with a reused Cholesky factor)
gives the integrator's linearised steps (max_newton=1) to round-off, for several models on one
factor, with Rayleigh damping, with a correction (the general damping path), and under gravity;
and it refuses a model of another mesh."""
import numpy as np
import pytest

from matlearn import _core, meshes
from matlearn.materials import Damping, Material, make_model
from matlearn.scene import vertices_in_box

G = np.array([0.0, -9.81, 0.0])


def _setup():
    mesh = meshes.bar(0.1, 0.02, 0.02, (6, 2, 2))
    fixed = vertices_in_box(np.asarray(mesh.vertices), [[-1, -1, -1], [1e-6, 1, 1]])
    return mesh, fixed


def _stiffen(Fh, Fhdot):
    Fh = np.asarray(Fh)
    d = np.clip(Fh - 1.0, 0, None)
    J = np.zeros(Fh.shape + (3,))
    J[:, np.arange(3), np.arange(3)] = 3e6 * d
    return 1.5e6 * d**2, J, None, None


def test_matches_integrator_linearised_steps():
    mesh, fixed = _setup()
    n = mesh.num_vertices
    V = np.asarray(mesh.vertices, float)
    rng = np.random.default_rng(0)
    x0 = V + 2e-3 * rng.standard_normal(V.shape) * (V[:, :1] > 1e-6)
    v0 = 0.05 * rng.standard_normal(V.shape) * (V[:, :1] > 1e-6)
    models = [
        make_model(mesh, Material("corotated", 5e5, 0.4, 1000.0), Damping(0.0, 0.002)),
        make_model(mesh, Material("corotated", 8e5, 0.3, 1200.0), Damping(3.0, 0.004, [], [0.1, 20.0])),
        make_model(mesh, Material("neo_hookean", 6e5, 0.45, 1000.0), Damping(1.0, 0.001),
                   _core.correction.PythonCorrection(_stiffen)),
    ]
    R = _core.time.LinearisedReplay(models[0], fixed, 1e-3, G)
    f = np.zeros((n, 3))
    f[-4:, 2] = 0.01
    for model in models * 2:  # the second round reuses a factor of another model
        integ = _core.time.Integrator(model, fixed, 1e-3, G, max_newton=1)
        integ.set_state(x0, v0)
        Xa, Va = integ.simulate(40, f, 1)
        Xb, Vb = R.simulate(model, x0, v0, 40, f)
        assert Xb.shape == Xa.shape == (41, n, 3)
        assert np.abs(Xb - Xa).max() < 1e-10 * 0.1
        assert np.abs(Vb - Va).max() < 1e-7
        assert np.abs(Xa[-1] - Xa[0]).max() > 1e-4  # it moved: the comparison means something
    st = R.stats
    assert st["steps"] == 240 and st["factorizations"] < st["steps"] / 4


def test_rejects_other_mesh_and_bad_input():
    mesh, fixed = _setup()
    model = make_model(mesh, Material("corotated", 5e5, 0.4, 1000.0), Damping())
    R = _core.time.LinearisedReplay(model, fixed, 1e-3, G)
    other = meshes.bar(0.1, 0.02, 0.02, (5, 2, 2))
    om = make_model(other, Material("corotated", 5e5, 0.4, 1000.0), Damping())
    V = np.asarray(other.vertices)
    with pytest.raises(ValueError, match="mesh"):
        R.simulate(om, V, 0 * V, 3, 0 * V)
    with pytest.raises(ValueError):
        _core.time.LinearisedReplay(model, fixed, -1.0, G)


def test_problem_memo_returns_identical_predictions_and_tells_models_apart(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    import diagnosis_suite as ds
    from matlearn.diagnosis.effects import EffectContext, build_model
    from matlearn.diagnosis.problem import Problem

    spec = {"effects": [], "shape": {"kind": "bar", "L": 0.1, "W": 0.025, "H": 0.025, "cells": (4, 2, 2)},
            "truth": {}, "motions": [("load", "train", 0.04, 1.0), ("load", "test", 0.06, 2.0)],
            "E0": 1.5e6, "nu0": 0.4, "rho0": 1000.0, "duration": 0.05}
    path, _ = ds.build_case(tmp_path, "memo", spec, seed=0, reuse=False)
    P, Q = Problem(path), Problem(path, reuse_factor=False)
    s = P.scene
    ctx = EffectContext(s.mesh, s.material, s.damping, s.fixed)
    rec = P.train[0]
    for params in ({}, {"stiffness_scale": [0.2]}, {"rayleigh_damping": [0.0, 0.3]},
                   {"compression_nonlinearity": [0.5]}):
        a = P.predict(build_model(ctx, params), rec)
        b = P.predict(build_model(ctx, params), rec)  # a new, equal model: from the memo
        c = Q.predict(build_model(ctx, params), Q.train[0])  # plain integrator, no memo
        assert np.array_equal(a, b) and np.abs(a - c).max() < 1e-12
    assert P.memo_hits == 4 and P.simulations == 4
    fps = {P.fingerprint(build_model(ctx, p)) for p in
           ({}, {"stiffness_scale": [1e-6]}, {"rayleigh_damping": [1e-6, 0]}, {"density": [1e-6]},
            {"tension_nonlinearity": [1e-3]}, {"poisson_ratio": [1e-6]})}
    assert len(fps) == 6
