"""The time step's refresh rule (cpp/time/integrator.cpp) and why a learned stress must be
isotropic (cpp/correction MlpCorrection's blend at coincident stretches).

* Refresh rule, read from the per-iteration update history (Integrator.last_timings["updates"]:
  |dv|, negative for an iteration on a freshly factorised tangent): an iteration on the reused
  factorisation whose update did not shrink by reuse_ratio is always followed by a fresh one, and
  the reused factorisation continues only after updates that did shrink that much.
* A correction whose principal stresses differ at coincident stretches (here a constant
  (c, -c, 0) Pa from an MLP with zero last layer) makes the stress depend on the arbitrary principal
  frame there: the force jumps, the iteration cycles, and steps end at the factorisation limit
  without converging. The same network through the isotropic blend converges every step, with a
  fraction of the factorisations."""
import numpy as np

from matlearn import _core, meshes
from matlearn.materials import Damping, Material
from matlearn.scene import Scene

L, MAX_NEWTON, RATIO = 0.08, 8, 0.25


def _scene():
    mesh = meshes.bar(L, 0.02, 0.02, cells=(4, 1, 1))
    V = np.asarray(mesh.vertices)
    return Scene(mesh=mesh, material=Material("corotated", 1e5, 0.3, 1000.0), damping=Damping(0.0, 0.002),
                 fixed=np.flatnonzero(V[:, 0] < 1e-9), time_step=1e-3)


def _offset_mlp(c, width):
    """An MLP whose stress outputs are the constant (c, -c, 0) Pa and dalpha 0."""
    rng = np.random.default_rng(0)
    layers = [(rng.standard_normal((6, 6)), rng.standard_normal(6)), (rng.standard_normal((6, 6)), np.zeros(6)),
              (np.zeros((4, 6)), np.zeros(4))]
    layers[0][0][:, 3:] = 0
    in_mean, in_std = np.r_[np.ones(3), np.zeros(3)], np.r_[0.01 * np.ones(3), np.ones(3)]
    kw = {} if width is None else {"isotropic_width": width}
    return _core.correction.MlpCorrection(layers, in_mean, in_std, np.r_[c, -c, 0.0, 0.0], np.ones(4), **kw)


def _run(sc, corr, steps=60):
    """Sag under gravity from rest: per-step update histories and factorisation counts."""
    integ = _core.time.Integrator(sc.model(corr), sc.fixed, sc.time_step, np.array([0, -9.81, 0.0]),
                                  MAX_NEWTON, 1e-7)
    n = sc.mesh.num_vertices
    integ.set_state(np.asarray(sc.mesh.vertices, float), np.zeros((n, 3)))
    hist, facts = [], []
    for _ in range(steps):
        integ.step(np.zeros((n, 3)))
        t = integ.last_timings
        hist.append(np.asarray(t["updates"]))
        facts.append(t["factorizations"])
        assert (hist[-1] < 0).sum() == facts[-1]
    return hist, np.array(facts)


def _check_refresh_rule(hist):
    chords = stalls = 0
    for u in hist:  # (the first iteration of a step may reuse the last step's factorisation)
        for k in range(1, len(u)):
            if u[k] > 0:  # an iteration on the reused factorisation
                chords += 1
                prev = abs(u[k - 1])
                if u[k] > RATIO * prev and k + 1 < len(u):
                    stalls += 1
                    assert u[k + 1] < 0, (k, u)  # not contracting enough: the next is fresh
                if k + 1 < len(u) and u[k + 1] > 0:
                    assert u[k] <= RATIO * prev, (k, u)  # reuse continues only after a contraction
    return chords, stalls


def test_refresh_rule_and_anisotropic_stress_stall():
    sc = _scene()
    raw_hist, raw_facts = _run(sc, _offset_mlp(300.0, 0.0))
    chords, stalls = _check_refresh_rule(raw_hist)
    assert chords > 20 and stalls > 5  # both branches of the rule are exercised
    # The anisotropic stress: the iteration cycles, steps end at the factorisation limit.
    assert (raw_facts == MAX_NEWTON).sum() >= 5, raw_facts

    blend_hist, blend_facts = _run(sc, _offset_mlp(300.0, None))
    _check_refresh_rule(blend_hist)
    assert blend_facts.max() < MAX_NEWTON  # every step converged
    assert blend_facts.sum() < raw_facts.sum() / 4, (blend_facts.sum(), raw_facts.sum())
