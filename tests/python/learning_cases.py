"""The small learning case shared by the loop and end-to-end tests: a neo-Hookean bar learned
from a co-rotated nominal model (release from a tip load; the test pulls harder)."""
from __future__ import annotations

from matlearn import meshes
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
