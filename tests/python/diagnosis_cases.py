"""Tiny synthetic cases for the diagnosis tests: truth on a finer mesh than the model's."""
import numpy as np

from matlearn import meshes
from matlearn.materials import Damping, Material
from matlearn.synthetic import Motion, make_case

L, W = 0.08, 0.02
E0 = 3e5


def tiny_case(tmp, name, E_scale=1.0, region=None, region_scale=1.0, seed=0, cells=(5, 2, 2), refine=2,
              noise=1e-6):
    """A clamped bar released from two bends (train) and one mixed load (test); the truth on a
    mesh `refine` times finer than the model's (1: the model's own mesh)."""
    model = meshes.bar(L, W, W, cells)
    truth = meshes.bar(L, W, W, tuple(refine * c for c in cells))
    C = np.asarray(truth.vertices)[np.asarray(truth.tets)].mean(axis=1)
    E = np.full(truth.num_tets, E0 * E_scale)
    if region is not None:
        E[(C[:, 0] >= region[0] * L) & (C[:, 0] <= region[1] * L)] *= region_scale
    tip = [[0.75 * L, -1, -1], [1, 1, 1]]
    motions = [
        Motion("release", "train", 0.1, load={"box": tip, "force": [0, -0.25, 0.1]}),
        Motion("release", "train", 0.1, twist={"box": tip, "torque": [0.004, 0, 0]}),
        Motion("release", "test", 0.1, load={"box": tip, "force": [0.05, 0.15, -0.2]}),
    ]
    return make_case(tmp, name, truth, Material("corotated", E, 0.4, 1000.0), Damping(0, 0.002),
                     model, Material("corotated", E0, 0.4, 1000.0), Damping(0, 0.002),
                     [[-1, -1, -1], [1e-6, 1, 1]], motions, marker_fraction=0.5, noise=noise,
                     seed=seed)


def model_region(region, cells=(5, 2, 2)):
    model = meshes.bar(L, W, W, cells)
    C = np.asarray(model.vertices)[np.asarray(model.tets)].mean(axis=1)
    return np.flatnonzero((C[:, 0] >= region[0] * L) & (C[:, 0] <= region[1] * L))


FAST = dict(patches=6, refine_top=2, report=False)
