"""Synthetic analogues of the rows of the paper's Table 1 (method.md section 8), built with
`synthetic.make_case`. Each case has a ground-truth law and damping (hidden in truth.json), the
nominal model given to the learner, a clamp, train recordings and held-out test recordings, the
last of which has a clearly larger deformation than training.

Sizes are kept small (a few hundred vertices, 0.3 s at h = 1 ms) so the whole benchmark runs on a
shared 2-core machine; the paper used 5k-20k tets and 1-4 s recordings. Deviations from the
paper's parameters are listed in each case's `notes`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import meshes
from .materials import Damping, Material
from .synthetic import Motion, make_case

PAPER_ERROR = {"turtle": 2.8, "dragon": 0.4, "sphere_tension": 4.1, "sphere_compression": 6.0,
               "bar_damping_1": 0.1, "bar_damping_2": 0.8, "layered_bar": 0.2}
TARGET_ERROR = {"turtle": 1.4, "dragon": 0.2, "sphere_tension": 2.0, "sphere_compression": 3.0,
                "bar_damping_1": 0.05, "bar_damping_2": 0.4, "layered_bar": 0.1}


@dataclass
class CaseSpec:
    name: str
    kwargs: dict
    notes: str = ""
    learn: dict = field(default_factory=dict)


def _release(role, box, force, duration=0.3, twist=None):
    load = {"box": box, "force": list(force)} if force is not None else None
    tw = {"box": box, "torque": list(twist)} if twist is not None else None
    return Motion("release", role, duration, load=load, twist=tw)


def _updown(role, box, amp, duration=0.3):
    kf = [[0.0, [0, 0, 0]], [0.08, [0, amp, 0]], [0.16, [0, -amp, 0]], [0.24, [0, 0, 0]]]
    return Motion("drive", role, duration, drive={"box": box, "keyframes": kf})


def turtle(fraction=0.13):
    mesh = meshes.capsule(radius=0.03, length=0.05, max_volume=(0.03 / 1.6) ** 3)
    V = np.asarray(mesh.vertices)
    x0, x1 = V[:, 0].min(), V[:, 0].max()
    clamp = [[-1, -1, -1], [x0 + 0.012, 1, 1]]
    tip = [[x1 - 0.02, -1, -1], [1, 1, 1]]
    return CaseSpec("turtle", dict(
        truth_mesh=mesh, truth_material=Material("neo_hookean", 2e4, 0.43, 1000.0),
        truth_damping=Damping(0.0, 0.005), model_mesh=mesh,
        nominal_material=Material("corotated", 3.5e4, 0.43, 1000.0), nominal_damping=Damping(0.0, 0.005),
        fixed_box=clamp, marker_fraction=fraction,
        motions=[_release("train", tip, [0, 0.6, 0.2]), _release("test", tip, [0, 0.5, -0.3]),
                 _release("test", tip, [0, 1.0, 0.0])]),
        notes="compound 'turtle-like' stand-in: a stubby capsule clamped at one end; "
              f"{mesh.num_tets} tets; {int(round(100 * fraction))}% of surface vertices as markers")


def dragon(fraction=0.06):
    mesh = meshes.bar(0.12, 0.03, 0.025, cells=(8, 2, 2))
    tip = [[0.105, -1, -1], [1, 1, 1]]
    return CaseSpec("dragon", dict(
        truth_mesh=mesh, truth_material=Material("stvk", 1e5, 0.40, 1000.0),
        truth_damping=Damping(0.0, 0.005), model_mesh=mesh,
        nominal_material=Material("corotated", 1.2e5, 0.40, 1000.0), nominal_damping=Damping(0.0, 0.005),
        fixed_box=[[-1, -1, -1], [1e-4, 1, 1]], marker_fraction=fraction,
        motions=[_release("train", tip, [0, 0.5, 0.2], twist=[0.004, 0, 0]),
                 _release("test", tip, [0, 0.4, -0.3]), _release("test", tip, [0, 0.9, 0.0])]),
        notes="stand-in shape: a bar; StVK truth vs co-rotated nominal; "
              f"{int(round(100 * fraction))}% of surface vertices as markers")


def _sphere_case(name, edit, fraction=1.0):
    mesh = meshes.sphere(radius=0.05, subdivisions=1, max_volume=(0.05 / 2.2) ** 3)
    top = [[-1, 0.032, -1], [1, 1, 1]]
    bottom = [[-1, -1, -1], [1, -0.035, 1]]
    truth = Material("designed", 1.2e5 / 1.2, 0.40, 1000.0, edits=[edit])
    return CaseSpec(name, dict(
        truth_mesh=mesh, truth_material=truth, truth_damping=Damping(0.0, 0.02), model_mesh=mesh,
        nominal_material=Material("corotated", 1.2e5, 0.40, 1000.0), nominal_damping=Damping(0.0, 0.01),
        fixed_box=bottom, marker_fraction=fraction, gravity=(0.0, -9.81, 0.0),
        motions=[_updown("train", top, 0.01), _updown("test", top, 0.008), _updown("test", top, 0.015)]),
        notes="neo-Hookean E=1e5 with a spline-like bump edit of the principal stress; top cap "
              "keyframed up-down, bottom clamped; truth alpha_K=0.02 s (paper 0.2 s, which makes "
              "the driven sphere quasi-static at our size); last test has 1.5x the train amplitude")


def sphere_tension():
    return _sphere_case("sphere_tension", (3e4, 1.12, 0.1))


def sphere_compression():
    return _sphere_case("sphere_compression", (-3e4, 0.88, 0.1))


def _damping_bar(name, poly):
    mesh = meshes.bar(0.12, 0.02, 0.02, cells=(8, 2, 2))
    tip = [[0.105, -1, -1], [1, 1, 1]]
    return CaseSpec(name, dict(
        truth_mesh=mesh, truth_material=Material("corotated", 3e5, 0.40, 1000.0),
        truth_damping=Damping(0.0, 0.004, stiffness_poly=poly), model_mesh=mesh,
        nominal_material=Material("corotated", 3e5, 0.40, 1000.0), nominal_damping=Damping(0.0, 0.004),
        fixed_box=[[-1, -1, -1], [1e-4, 1, 1]], marker_fraction=1.0,
        motions=[_release("train", tip, [0, 0.25, 0.1]), _release("test", tip, [0, 0.2, -0.1]),
                 _release("test", tip, [0, 0.45, 0.0])]),
        notes=f"co-rotated truth with alpha_K(s1) = 0.004 + poly {poly} in (s1 - 1); nominal "
              "constant alpha_K = 0.004 s")


def bar_damping_1():
    return _damping_bar("bar_damping_1", [0.05])


def bar_damping_2():
    return _damping_bar("bar_damping_2", [0.3, 2.0])


def _coarsened_bar_case(name, fine, E, coarse, notes):
    """A co-rotated truth with per-tet Young's modulus E (Pa) on the fine bar, learned on `coarse`
    with the nominal E = 3e6 Pa: trained on a bend in y and a twist, tested on a bend in z and on a
    larger bend in y with a twist (the layered-bar rows)."""
    tip = [[0.105, -1, -1], [1, 1, 1]]
    return CaseSpec(name, dict(
        truth_mesh=fine, truth_material=Material("corotated", E, 0.40, 1000.0),
        truth_damping=Damping(0.0, 0.002), model_mesh=coarse,
        nominal_material=Material("corotated", 3e6, 0.40, 1000.0), nominal_damping=Damping(0.0, 0.002),
        fixed_box=[[-1, -1, -1], [1e-4, 1, 1]], marker_fraction=1.0,
        motions=[_release("train", tip, [0, 0.6, 0.0]), _release("train", tip, None, twist=[0.004, 0, 0]),
                 _release("test", tip, [0, 0, 0.6]), _release("test", tip, [0, 1.0, 0.0], twist=[0.004, 0, 0])]),
        notes=notes)


def _alternating_layers(mesh, cells, axis):
    """Per-tet layer label 0/1 alternating with the fine cell index along `axis` (layers one fine
    cell thick)."""
    V = np.asarray(mesh.vertices)
    lo, hi = V[:, axis].min(), V[:, axis].max()
    c = V[mesh.tets].mean(axis=1)[:, axis]
    return (np.floor((c - lo) / (hi - lo) * cells[axis]).astype(np.int64) % 2)


def layered_bar():
    cells = (8, 4, 4)
    fine = meshes.bar(0.12, 0.02, 0.02, cells=cells)
    coarse = meshes.bar(0.12, 0.02, 0.02, cells=tuple(c // 2 for c in cells))
    E = np.where(_alternating_layers(fine, cells, axis=2) == 1, 1e7, 1e5)
    return _coarsened_bar_case(
        "layered_bar", fine, E, coarse,
        notes="paper Fig. 17: truth on a fine 8x4x4-cell bar whose materials E=1e5 / 1e7 alternate layer by "
              "layer, one fine cell thick, stacked in z (4 layers, soft at the bottom); model: co-rotated "
              "E=3e6 on the 4x2x2-cell mesh coarsened by 2 in each axis, so every coarse cell holds one "
              "layer of each material; trained on a bend in y (along the layers) and a twist; test 1 bends "
              "in z (across the layers), test 2 bends in y and twists. Layer axis (the paper does not state "
              "it): z, a laminate stacked in height. Layers across the length (x) were tried: the soft "
              "slabs in series make the composite so soft (effective E ~1.2e5) that gravity sags the bar "
              "by ~25 % of its length; hung along its axis (gravity +x) with 1/12 of the bend loads, the "
              "coarse model stayed at its E fit (0.48 % train, 0.64 % held-out, 3 iterations without an "
              "accepted update): the strain concentrates in one tet layer per soft slab, which no coarse "
              "tet resolves")


def layered_bar_halves():
    fine, layer = meshes.layered_bar(0.12, 0.02, 0.02, cells=(8, 2, 4))
    coarse = meshes.bar(0.12, 0.02, 0.02, cells=(4, 1, 2))
    E = np.where(layer == 1, 1e7, 1e5)
    return _coarsened_bar_case(
        "layered_bar_halves", fine, E, coarse,
        notes="extra row, no target (the layered bar of sessions 1-5): the truth's bottom half (z < 0) "
              "E=1e5, top half 1e7, on a fine 8x2x4-cell mesh, so every cell of the 4x1x2-cell coarse "
              "model is of one material; model: co-rotated E=3e6; trained on a bend and a twist")


ALL = [turtle, dragon, sphere_tension, sphere_compression, bar_damping_1, bar_damping_2, layered_bar,
       layered_bar_halves]


def build(spec: CaseSpec, out_dir, seed: int = 0):
    """Write the case and return its scene path."""
    return make_case(out_dir, spec.name, seed=seed, **spec.kwargs)
