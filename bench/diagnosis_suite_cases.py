"""Cases of the withheld-effect benchmark (bench/diagnosis_suite.py): shapes, truths with one or
two effects, and lab-like motions.

Every case is an experiment a lab could record: the body is clamped, held under a load found by
a static solve and released (bending load or twist), dropped from rest under gravity, or tapped
(an initial velocity; the recording starts at the swing's turning point), and its surface
markers (a fraction of the surface vertices, small noise) are recorded during the free
vibration. Train recordings have moderate amplitudes; the test recording is larger and in
another direction. The truth lives on a finer mesh than the model (1.5x in cells for boxes, a
smaller volume bound on the same surface for TetGen shapes, so markers lie on the model's
surface, as when the mesh is made from a scan), so a discretisation gap exists as with real
data. Load amplitudes are set from the nominal model's linear compliance, so a "4 % deflection"
means the same on every shape.

`named_specs()` is the fixed development set (14 named cases); `random_specs(seed, n)` draws a
second set (effect, shape, magnitude, sign, combination, motions) from the seed alone.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

from matlearn import _core, meshes
from matlearn.materials import Damping, Material, make_model
from matlearn.scene import vertices_in_box
from matlearn.synthetic import Motion

NOMINAL_DAMPING = (0.0, 0.002)
EFFECTS = ("stiffness_scale", "poisson_ratio", "tension_nonlinearity", "compression_nonlinearity",
           "rayleigh_damping", "strain_dependent_damping", "heterogeneity", "density",
           "support_compliance", "history_dependence")
BIG = 1.0  # box bounds beyond any shape (m)


# ------------------------------------------------------------------ truths outside the families
class DamageCorrection:
    """History-dependent truth (Mullins-like damage): each element softens by
    d = min(dmax, k * max-so-far |s - 1|); the state persists across steps and recordings."""

    def __init__(self, mu, lam, k, dmax):
        self.mu, self.lam, self.k, self.dmax = mu, lam, k, dmax
        self.peak = None

    def __call__(self, Fh, Fhdot):
        Fh = np.asarray(Fh)
        e = Fh - 1.0
        if self.peak is None or len(self.peak) != len(Fh):
            self.peak = np.zeros(len(Fh))
        self.peak = np.maximum(self.peak, np.abs(e).max(axis=1))
        d = np.minimum(self.dmax, self.k * self.peak)[:, None]
        P = 2 * self.mu[:, None] * e + self.lam[:, None] * e.sum(axis=1, keepdims=True)
        J = np.zeros((len(Fh), 3, 3))
        J[:] = -(self.lam[:, None, None] * np.ones((3, 3)) + 2 * self.mu[:, None, None] * np.eye(3))
        return -d * P, d[:, :, None] * J, None, None


class PlasticSetCorrection:
    """History-dependent truth of another mechanism than damage: plastic set. Per element and
    sorted principal strain e = s - 1 (sorted, so the state is a continuous function of the
    motion) the extremes reached so far are remembered; beyond a yield strain ey the excess
    becomes a permanent strain ep = (max e - ey)+ + (min e + ey)-, at most pmax in size
    (saturating: a far Newton trial point cannot leave an unbounded set), and the stress loses
    c * 2 mu * ep. On first loading past ey the body is softer, on unloading it is elastic
    again around a shifted rest shape (a permanent set, loops that differ in loading and
    unloading); the state persists across steps and recordings and only grows (as damage does),
    so the truth's Newton solves stay well posed."""

    def __init__(self, mu, c, ey, pmax):
        self.mu, self.c, self.ey, self.pmax = mu, c, ey, pmax
        self.hi = self.lo = None

    def __call__(self, Fh, Fhdot):
        e = np.asarray(Fh) - 1.0
        m = len(e)
        if self.hi is None or len(self.hi) != m:
            self.hi, self.lo = np.zeros((m, 3)), np.zeros((m, 3))
        order = np.argsort(-e, axis=1, kind="stable")
        rows = np.arange(m)[:, None]
        es = e[rows, order]
        top = self.ey + self.pmax
        flowing = ((es > self.hi) & (es > self.ey) & (es < top)) | ((es < self.lo) & (es < -self.ey) & (es > -top))
        self.hi, self.lo = np.clip(np.maximum(self.hi, es), 0, top), np.clip(np.minimum(self.lo, es), -top, 0)
        ep = np.clip(self.hi - self.ey, 0, None) + np.clip(self.lo + self.ey, None, 0)
        # where two principal strains meet (they swap places in the sorted order), their sets
        # are blended to the mean, so the stress stays continuous through the swap
        k = self.c * 2.0 * self.mu[:, None]
        q, dq = ep.copy(), np.where(flowing, 1.0, 0.0)
        for i in (0, 1):
            g = np.clip((es[:, i] - es[:, i + 1]) / self.ey, 0.0, 1.0)[:, None]
            a, b = q[:, i:i + 1].copy(), q[:, i + 1:i + 2].copy()
            q[:, i:i + 1] = 0.5 * (1 + g) * a + 0.5 * (1 - g) * b
            q[:, i + 1:i + 2] = 0.5 * (1 - g) * a + 0.5 * (1 + g) * b
        P = np.zeros_like(e)
        P[rows, order] = -k * q
        d = np.zeros_like(e)
        d[rows, order] = -k * dq
        J = np.zeros((m, 3, 3))
        J[:, np.arange(3), np.arange(3)] = d
        return P, J, None, None


class SidePoly:
    """One-sided nonlinearity of a shape unlike the diagnosis family: exponential
    stiffening/softening E * a * (exp(b d) - 1 - b d) / b on one side of s = 1 (side +1: tension,
    -1: compression; a < 0 softens), continued linearly (C1) beyond the stretch `d_cap` where
    the added tangent E a (exp(b d) - 1) reaches 99 E a (stiffening) or leaves a quarter of the
    nominal tangent E (softening). The truth's motions stay far inside it; without the cap a
    Newton iterate of the truth's static hold that overshoots (stretch 3.5x, exp(105)) or a
    softening whose total tangent turns negative made the truth unbuildable (random seeds 3-5)."""

    def __init__(self, E, a, b, side):
        self.E, self.a, self.b, self.side = E, a, b, side
        growth = 100.0 if a > 0 else 1.0 + 0.75 / abs(a)  # exp(b d_cap)
        self.d_cap = float(np.log(growth) / b)

    def _law(self, d):
        E, a, b = self.E, self.a, self.b
        return E * a * (np.exp(b * d) - 1 - b * d) / b, E * a * (np.exp(b * d) - 1)

    def __call__(self, Fh, Fhdot):
        Fh = np.asarray(Fh)
        d = np.clip(self.side * (Fh - 1.0), 0, None)
        p_cap, dd_cap = self._law(self.d_cap)
        p, dd = self._law(np.minimum(d, self.d_cap))
        beyond = d > self.d_cap
        p = np.where(beyond, p_cap + dd_cap * (d - self.d_cap), p)
        dd = np.where(beyond, dd_cap, dd)
        P = self.side * p
        J = np.zeros(Fh.shape + (3,))
        J[:, np.arange(3), np.arange(3)] = dd
        return P, J, None, None


# ------------------------------------------------------------------ shapes
def _capsule(radius, length, count, max_volume):
    import trimesh

    s = trimesh.creation.capsule(height=length, radius=radius, count=count)
    s.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return meshes.tetrahedralize(s.vertices, s.faces, max_volume=max_volume, min_ratio=2.0)


def make_shape(shape: dict):
    """(model mesh, truth mesh, clamp box, tip box, axis (3,), length along the axis).
    shape: {"kind": "bar"|"plate", "L", "W", "H", "cells", optional "truth_factor" (1.5)} | {"kind": "capsule", "r", "L"} |
    {"kind": "sphere", "r"}. Bars/plates lie along +x from a clamp at x = 0; capsules along x,
    clamped at their -x cap; spheres clamped at the bottom (-y, against gravity)."""
    kind = shape["kind"]
    if kind in ("bar", "plate"):
        L, W, H, cells = shape["L"], shape["W"], shape["H"], tuple(shape["cells"])
        model = meshes.bar(L, W, H, cells)
        k = shape.get("truth_factor", 1.5)
        truth = meshes.bar(L, W, H, tuple(int(np.ceil(k * c)) for c in cells))
        return (model, truth, [[-BIG, -BIG, -BIG], [1e-6, BIG, BIG]],
                [[0.8 * L, -BIG, -BIG], [BIG, BIG, BIG]], np.array([1.0, 0, 0]), L)
    if kind == "capsule":
        r, L = shape["r"], shape["L"]
        mv = 0.6 * r**3
        model = _capsule(r, L, [8, 6], mv)
        truth = _capsule(r, L, [8, 6], mv / 8)  # same surface: markers lie on the model's
        x0 = -(L / 2 + r)
        return (model, truth, [[-BIG, -BIG, -BIG], [x0 + 0.35 * r, BIG, BIG]],
                [[-x0 - 0.7 * r, -BIG, -BIG], [BIG, BIG, BIG]], np.array([1.0, 0, 0]), L + 2 * r)
    if kind == "sphere":
        r = shape["r"]
        mv = 0.05 * r**3
        model = meshes.sphere(r, max_volume=mv, subdivisions=1, min_ratio=2.0)
        truth = meshes.sphere(r, max_volume=mv / 3.375, subdivisions=1, min_ratio=2.0)
        return (model, truth, [[-BIG, -BIG, -BIG], [BIG, -0.7 * r, BIG]],
                [[-BIG, 0.6 * r, -BIG], [BIG, BIG, BIG]], np.array([0, 1.0, 0]), 2 * r)
    raise ValueError(f"unknown shape kind {kind!r}")


def _along(mesh, axis):
    C = np.asarray(mesh.vertices)[np.asarray(mesh.tets)].mean(axis=1)
    s = C @ axis
    V = np.asarray(mesh.vertices) @ axis
    return (s - V.min()) / (V.max() - V.min())


def _transverse(axis, angle):
    """Unit vector perpendicular to `axis` at `angle` (rad) from the gravity-side direction."""
    g = np.array([0, -1.0, 0])
    e1 = g - (g @ axis) * axis
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.array([1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    return np.cos(angle) * e1 + np.sin(angle) * e2


# ------------------------------------------------------------------ compliance and motions
def _compliance(mesh, material, fixed, tip_box):
    """Max tip displacement per N of a tip load (per transverse direction) and per N m of twist,
    from the nominal model's linear stiffness at rest; plus the tip mass and total mass."""
    model = make_model(mesh, material, Damping())
    V = np.asarray(mesh.vertices, float)
    n = len(V)
    K = model.stiffness(V, np.zeros_like(V)).tocsc()
    free = np.setdiff1d(np.arange(n), fixed)
    dofs = (3 * free[:, None] + np.arange(3)).ravel()
    solve = spla.factorized(K[dofs][:, dofs].tocsc())
    tip = np.setdiff1d(vertices_in_box(V, tip_box), fixed)
    m = np.asarray(model.vertex_mass, float)

    def response(f):
        u = np.zeros(3 * n)
        u[dofs] = solve(f.ravel()[dofs])
        return np.linalg.norm(u.reshape(n, 3)[tip], axis=1).max()

    return response, tip, m


def build_motions(spec, mesh, material, fixed, tip_box, axis, length, rng):
    """Motions of a spec (duration spec["duration"], default ~2.5 periods of the lowest mode
    estimated from the tip compliance, 0.15-0.3 s): spec["motions"] = [(kind, role, amplitude (fraction of the length),
    angle (rad, about the axis, from the gravity side))]; kind in load, twist, drop, flick."""
    from matlearn.synthetic import hold_forces

    response, tip, m = _compliance(mesh, material, fixed, tip_box)
    k_tip = 1.0 / response(hold_forces(mesh, m, Motion("release", load={"box": tip_box,
                                                                        "force": list(_transverse(axis, 0.0))}), fixed))
    m_eff = 0.24 * m.sum()
    period = 2 * np.pi / np.sqrt(k_tip / m_eff)
    dur = float(spec.get("duration") or np.clip(2.5 * period, 0.15, 0.3))
    out = []
    for kind, role, amp, angle in spec["motions"]:
        target = amp * length
        d = _transverse(axis, angle)
        if kind == "load":
            unit = hold_forces(mesh, m, Motion("release", load={"box": tip_box, "force": list(d)}), fixed)
            F = target / response(unit)
            out.append(Motion("release", role, dur, load={"box": tip_box, "force": list(F * d)}, load_steps=12))
        elif kind == "twist":
            unit = hold_forces(mesh, m, Motion("release", twist={"box": tip_box, "torque": list(axis)}), fixed)
            tq = target / response(unit)
            # a little bending with the twist, so both moduli are seen
            Fb = 0.3 * target / response(hold_forces(mesh, m, Motion("release", load={
                "box": tip_box, "force": list(d)}), fixed))
            out.append(Motion("release", role, dur, twist={"box": tip_box, "torque": list(tq * axis)},
                              load={"box": tip_box, "force": list(Fb * d)}, load_steps=12))
        elif kind == "drop":
            out.append(Motion("release", role, dur))
        elif kind == "flick":
            v = 1.3 * target * np.sqrt(k_tip / m[tip].sum()) * np.sqrt(m[tip].sum() / m_eff)
            out.append(Motion("flick", role, dur, velocity={"box": tip_box, "velocity": list(v * d)},
                              max_preroll=1.5 * period))
        else:
            raise ValueError(f"unknown motion kind {kind!r}")
    return out


# ------------------------------------------------------------------ truths
def build_truth(spec, truth_mesh, model_mesh, axis, clamp):
    """(truth Material, truth Damping, correction or None, model elements of the true region or
    None) for spec["truth"] = {effect: parameters}. A compliant support is the layer of
    elements within `depth` (fraction of the length) beyond the clamp box."""
    E0, nu0, rho0 = spec["E0"], spec["nu0"], spec["rho0"]
    tr = spec["truth"]
    m = truth_mesh.num_tets
    E = np.full(m, E0 * tr.get("stiffness_scale", 1.0))
    s_truth, s_model = _along(truth_mesh, axis), _along(model_mesh, axis)
    region_model = None
    if "heterogeneity" in tr:
        a, b, scale = tr["heterogeneity"]
        E[(s_truth >= a) & (s_truth <= b)] *= scale
        region_model = np.flatnonzero((s_model >= a) & (s_model <= b))
    if "support_compliance" in tr:
        depth, scale = tr["support_compliance"]
        V = np.asarray(truth_mesh.vertices)
        s_v = V @ axis
        s_clamp = (s_v[vertices_in_box(V, clamp)].max() - s_v.min()) / (s_v.max() - s_v.min())
        E[s_truth < s_clamp + depth] *= scale
    nu = tr.get("poisson_ratio", nu0)
    rho = rho0 * tr.get("density", 1.0)
    mat = Material("corotated", E, nu, rho)
    am, ak = NOMINAL_DAMPING
    if "rayleigh_damping" in tr:
        am, ak = tr["rayleigh_damping"]
    poly = list(tr.get("strain_dependent_damping", []))
    damping = Damping(am, ak, [], poly)
    correction = None
    if "tension_nonlinearity" in tr or "compression_nonlinearity" in tr:
        side = 1.0 if "tension_nonlinearity" in tr else -1.0
        a, b = tr.get("tension_nonlinearity", tr.get("compression_nonlinearity"))
        correction = _core.correction.PythonCorrection(SidePoly(E0, a, b, side))
    if "history_dependence" in tr:
        mu, lam = mat.lame(m)
        correction = _core.correction.PythonCorrection(DamageCorrection(mu, lam, *tr["history_dependence"]))
    if "plastic_set" in tr:  # a second history mechanism (named set only)
        mu, _ = mat.lame(m)
        correction = _core.correction.PythonCorrection(PlasticSetCorrection(mu, *tr["plastic_set"]))
    return mat, damping, correction, region_model


def min_youngs(shape: dict, rho: float, sag: float = 0.03) -> float:
    """Young's modulus below which gravity alone sags a cantilever by more than `sag` of its
    length (beam estimate 1.5 rho g L^4 / (E t^2), t the thickness along gravity): keeps drops
    and holds moderate on floppy shapes."""
    if shape["kind"] in ("bar", "plate"):
        L, t = shape["L"], shape["W"]
    elif shape["kind"] == "capsule":
        L, t = shape["L"] + 2 * shape["r"], 2 * shape["r"]
    else:
        return 0.0
    return 1.5 * rho * 9.81 * L**3 / (sag * t**2)


# ------------------------------------------------------------------ the named set
def _bar(L, W, H, cells):
    return {"kind": "bar", "L": L, "W": W, "H": H, "cells": cells}


def named_specs() -> dict:
    """name -> spec: effects (true), shape, nominal E0/nu0/rho0, truth parameters, motions."""
    B = dict(E0=8e5, nu0=0.4, rho0=1000.0)

    def case(effects, shape, truth, motions, **kw):
        out = {**B, **kw, "effects": effects, "shape": shape, "truth": truth, "motions": motions}
        out["E0"] = float(max(out["E0"], min_youngs(shape, out["rho0"])))
        return out

    std = [("load", "train", 0.04, 0.3), ("drop", "train", 0, 0), ("load", "test", 0.07, 2.0)]
    return {
        "control": case([], _bar(0.14, 0.035, 0.035, (8, 3, 3)), {}, std),
        "stiffness_scale": case(["stiffness_scale"], {"kind": "capsule", "r": 0.016, "L": 0.1},
                                {"stiffness_scale": 0.65},
                                [("load", "train", 0.04, 0.0), ("flick", "train", 0.04, 1.6),
                                 ("load", "test", 0.07, 2.4)]),
        "poisson_ratio": case(["poisson_ratio"], _bar(0.12, 0.04, 0.035, (7, 3, 3)), {"poisson_ratio": 0.22},
                              [("twist", "train", 0.03, 0.0), ("load", "train", 0.04, 1.2),
                               ("twist", "test", 0.05, 2.5)], nu0=0.42),
        "tension_nonlinearity": case(["tension_nonlinearity"], _bar(0.16, 0.035, 0.025, (10, 3, 2)),
                                     {"tension_nonlinearity": (3.0, 40.0)}, std),
        "compression_nonlinearity": case(["compression_nonlinearity"],
                                         {"kind": "plate", "L": 0.12, "W": 0.012, "H": 0.07, "cells": (8, 2, 5)},
                                         {"compression_nonlinearity": (2.5, 35.0)},
                                         [("load", "train", 0.05, 0.0), ("flick", "train", 0.04, 0.0),
                                          ("load", "test", 0.08, 3.1)], E0=1.2e6),
        "rayleigh_damping": case(["rayleigh_damping"], _bar(0.15, 0.032, 0.035, (8, 3, 3)),
                                 {"rayleigh_damping": (3.0, 0.0035)},
                                 [("load", "train", 0.04, 0.5), ("flick", "train", 0.04, 2.0),
                                  ("load", "test", 0.07, 1.5)]),
        "strain_dependent_damping": case(["strain_dependent_damping"], _bar(0.14, 0.035, 0.035, (8, 3, 3)),
                                         {"strain_dependent_damping": (0.1, 20.0)}, std, E0=6e5),
        "heterogeneity": case(["heterogeneity"], _bar(0.16, 0.035, 0.035, (9, 3, 3)),
                              {"heterogeneity": (0.35, 0.65, 0.35)},
                              [("load", "train", 0.04, 0.0), ("twist", "train", 0.03, 0.0),
                               ("load", "test", 0.07, 2.2)]),
        "density": case(["density"], {"kind": "sphere", "r": 0.035}, {"density": 1.5},
                        [("load", "train", 0.03, 1.57), ("drop", "train", 0, 0), ("load", "test", 0.05, 3.5)],
                        E0=2e5),
        "support_compliance": case(["support_compliance"], _bar(0.15, 0.035, 0.035, (8, 3, 3)),
                                   {"support_compliance": (0.06, 0.3)},
                                   [("load", "train", 0.04, 0.3), ("flick", "train", 0.04, 1.8),
                                    ("load", "test", 0.07, 2.8)]),
        "history_dependence": case(["history_dependence"], _bar(0.15, 0.035, 0.035, (8, 3, 3)),
                                   {"history_dependence": (8.0, 0.4)},
                                   [("drop", "train", 0, 0), ("load", "train", 0.05, 0.4),
                                    ("load", "test", 0.08, 2.0)]),
        # the same outcome from another mechanism, magnitude and second motion: a check of
        # generality (a virgin body first, as in every history case: a set formed before the first
        # recording is indistinguishable from another rest shape)
        "history_plasticity": case(["history_dependence"], _bar(0.15, 0.035, 0.035, (8, 3, 3)),
                                   {"plastic_set": (0.5, 0.003, 0.006)},
                                   [("drop", "train", 0, 0), ("flick", "train", 0.05, 1.8),
                                    ("load", "test", 0.07, 2.8)]),
        "combined_stiffness_damping": case(["stiffness_scale", "rayleigh_damping"],
                                           {"kind": "capsule", "r": 0.014, "L": 0.11},
                                           {"stiffness_scale": 0.75, "rayleigh_damping": (2.5, 0.003)},
                                           std),
        "combined_heterogeneity_tension": case(["heterogeneity", "tension_nonlinearity"],
                                               {"kind": "plate", "L": 0.14, "W": 0.014, "H": 0.06,
                                                "cells": (9, 2, 4)},
                                               {"heterogeneity": (0.0, 0.3, 2.5), "tension_nonlinearity": (2.0, 40.0)},
                                               [("load", "train", 0.05, 0.0), ("drop", "train", 0, 0),
                                                ("load", "test", 0.08, 2.6)], E0=1e6),
    }


# ------------------------------------------------------------------ the random set
def _random_shape(rng):
    kind = rng.choice(["bar", "bar", "plate", "capsule", "sphere"])
    if kind == "bar":
        L = rng.uniform(0.1, 0.2)
        W, H = rng.uniform(0.022, 0.045, 2)
        h = (L * W * H / 60.0) ** (1 / 3)  # ~60 cells, ~360 tets
        cells = tuple(int(max(2, min(12, round(d / h)))) for d in (L, W, H))
        return _bar(float(L), float(W), float(H), cells)
    if kind == "plate":
        L = rng.uniform(0.1, 0.16)
        W = rng.uniform(0.01, 0.016)
        H = rng.uniform(0.05, 0.09)
        return {"kind": "plate", "L": float(L), "W": float(W), "H": float(H),
                "cells": (int(round(L / H * 5)), 2, 5)}
    if kind == "capsule":
        return {"kind": "capsule", "r": float(rng.uniform(0.012, 0.02)), "L": float(rng.uniform(0.07, 0.13))}
    return {"kind": "sphere", "r": float(rng.uniform(0.025, 0.045))}


def _random_effect(rng, name, nu0):
    up = rng.random() < 0.5
    if name == "stiffness_scale":
        return float(rng.uniform(1.25, 1.7) if up else rng.uniform(0.6, 0.8))
    if name == "poisson_ratio":
        return float(nu0 - rng.uniform(0.12, 0.2)) if nu0 > 0.33 else float(min(0.48, nu0 + rng.uniform(0.1, 0.15)))
    if name in ("tension_nonlinearity", "compression_nonlinearity"):
        a = rng.uniform(1.5, 3.5) * (1 if rng.random() < 0.75 else -0.25)
        return (float(a), float(rng.uniform(25, 50)))
    if name == "rayleigh_damping":
        return (float(rng.uniform(1.5, 5.0)), float(NOMINAL_DAMPING[1] * rng.uniform(1.5, 3.0)))
    if name == "strain_dependent_damping":
        return (float(rng.uniform(0.0, 0.2)), float(rng.uniform(8, 25)))
    if name == "heterogeneity":
        w = rng.uniform(0.25, 0.4)
        a = rng.uniform(0.0, 1.0 - w)
        scale = rng.uniform(2.0, 3.0) if up else rng.uniform(0.3, 0.5)
        return (float(a), float(a + w), float(scale))
    if name == "density":
        return float(rng.uniform(1.3, 1.8) if up else rng.uniform(0.55, 0.75))
    if name == "support_compliance":
        return (float(rng.uniform(0.04, 0.08)), float(rng.uniform(0.2, 0.4)))
    if name == "history_dependence":
        return (float(rng.uniform(6, 10)), float(rng.uniform(0.3, 0.5)))
    raise ValueError(name)


def random_specs(seed: int, n: int = 10) -> dict:
    """n cases drawn from `seed` alone: shape, nominal material, 0-2 effects with random
    magnitudes and signs, and motions (two train, one larger test)."""
    rng = np.random.default_rng(seed)
    out = {}
    for i in range(n):
        u = rng.random()
        if u < 0.1:
            effects = []
        elif u < 0.3:
            pool = [e for e in EFFECTS if e != "history_dependence"]
            effects = list(rng.choice(pool, 2, replace=False))
            if {"stiffness_scale", "density"} <= set(effects):
                effects = ["stiffness_scale"]
            if {"tension_nonlinearity", "compression_nonlinearity"} <= set(effects):
                effects = [effects[0]]
        else:
            effects = [str(rng.choice(EFFECTS))]
        nu0 = float(rng.uniform(0.25, 0.45))
        shape = _random_shape(rng)
        truth = {e: _random_effect(rng, e, nu0) for e in effects}
        kinds = ["load", "twist", "drop", "flick"]
        first = str(rng.choice(["load", "flick"]))
        second = str(rng.choice(kinds))
        if "history_dependence" in effects:  # a virgin body first, then larger loads
            first, second = "drop", "load"
        motions = [(first, "train", float(rng.uniform(0.03, 0.05)), float(rng.uniform(0, 2 * np.pi))),
                   (second, "train", float(rng.uniform(0.03, 0.05)), float(rng.uniform(0, 2 * np.pi))),
                   (str(rng.choice(["load", "twist"])), "test", float(rng.uniform(0.06, 0.09)),
                    float(rng.uniform(0, 2 * np.pi)))]
        name = f"r{seed}_{i:02d}_" + ("+".join(effects) or "control")
        rho0 = float(rng.uniform(900, 1200))
        E0 = float(np.exp(rng.uniform(np.log(3e5), np.log(2e6))))
        out[name] = {"effects": [str(e) for e in effects], "shape": shape, "truth": truth,
                     "motions": motions, "E0": max(E0, min_youngs(shape, rho0)), "nu0": nu0,
                     "rho0": rho0}
    return out
