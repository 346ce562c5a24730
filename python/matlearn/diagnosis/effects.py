"""The library of candidate unmodelled effects (method.md section 9, formats.md vocabulary).

Every family is a small parameter vector `theta` (all zeros = the nominal model) that edits the
nominal material, damping or correction; several families compose into one C++ model. Parameters
are dimensionless and O(1) for a change that matters, so one finite-difference step and one trust
region fit all families:

* scales are logarithmic (theta = log factor);
* nonlinearities add a principal stress `E0 * d_ref * sum_k c_k (d / d_ref)^(k+1)` on one side of
  s = 1, d = s - 1 clipped to that side, d_ref the typical strain of the recordings;
* damping coefficients move by theta * (0.1 / omega) for alpha_K and theta * 0.1 omega for
  alpha_M: theta = 1 changes the damping ratio at the dominant frequency omega by about 0.05.

`history_dependence` has no stateless parameters: it is detected as inconsistency (history.py)
and reported as outside what a function of (Fh, Fhdot) can learn.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import _core
from ..materials import Damping, Material, make_model

VOCABULARY = (
    "stiffness_scale",
    "poisson_ratio",
    "tension_nonlinearity",
    "compression_nonlinearity",
    "rayleigh_damping",
    "strain_dependent_damping",
    "heterogeneity",
    "density",
    "support_compliance",
    "history_dependence",
    "unexplained",
)


@dataclass(frozen=True)
class Family:
    name: str
    parameters: tuple  # parameter names (theta order)
    # extra information-criterion parameters (e.g. a located region counts as chosen, not given)
    extra_dof: int = 0
    description: str = ""


FAMILIES = {
    f.name: f
    for f in (
        Family("stiffness_scale", ("log_scale",), 0, "uniform Young's modulus scale"),
        Family("poisson_ratio", ("delta_nu",), 0, "Poisson ratio change"),
        Family("tension_nonlinearity", ("c2", "c3"), 0, "stress polynomial for s > 1"),
        Family("compression_nonlinearity", ("c2", "c3"), 0, "stress polynomial for s < 1"),
        Family("rayleigh_damping", ("d_alpha_mass", "d_alpha_stiffness"), 0, "Rayleigh coefficients"),
        Family("strain_dependent_damping", ("d_alpha_mass", "d_alpha_stiffness", "c1", "c2"), 0,
               "Rayleigh damping with alpha_K a quadratic in s1 - 1 (nests rayleigh_damping)"),
        Family("heterogeneity", ("log_scale_region", "log_scale_rest"), 1,
               "stiffness of a located region relative to the rest of the body"),
        Family("density", ("log_scale",), 0, "uniform density scale"),
        Family("support_compliance", ("log_scale",), 0, "stiffness of the layer at the clamp"),
    )
}
CANDIDATES = tuple(FAMILIES)  # the stateless, simulated families
# Nuisance parameter: the coarse mesh's stiffness offset, free inside the plausible
# discretisation range (EffectContext.offset_range). Families that change the elastic response
# only in part (Poisson ratio, nonlinearity, damping, clamp) are fitted together with it, so the
# stiffness offset a coarse mesh needs is not mistaken for (or hidden from) them.
NUISANCE = "discretisation_offset"
WITH_NUISANCE = ("poisson_ratio", "tension_nonlinearity", "compression_nonlinearity",
                 "rayleigh_damping", "strain_dependent_damping", "support_compliance")


def n_params(name: str) -> int:
    return 1 if name == NUISANCE else len(FAMILIES[name].parameters)


@dataclass
class EffectContext:
    """What the families need to know about the nominal model and the data."""

    mesh: object
    material: Material
    damping: Damping
    fixed: np.ndarray
    d_ref: float = 0.05  # typical |principal strain| of the recordings
    omega: float = 30.0  # dominant angular frequency (rad/s)
    region: np.ndarray | None = None  # bool (#T): heterogeneity region
    clamp_layer: np.ndarray = field(default=None)  # bool (#T): elements touching the clamp
    # discretisation: log stiffness offset folded into `material` (baseline), the offset that
    # matches the once-refined mesh, and the plausible range (see discretisation.discretisation)
    offset_applied: float = 0.0
    offset_reference: float = 0.0
    offset_range: tuple = (0.0, 0.0)

    def __post_init__(self):
        if self.clamp_layer is None:
            self.clamp_layer = clamp_layer(self.mesh, self.fixed)


def clamp_layer(mesh, fixed) -> np.ndarray:
    """Elements with at least one clamped vertex (the compliant support layer)."""
    is_fixed = np.zeros(mesh.num_vertices, bool)
    is_fixed[np.asarray(fixed, int)] = True
    return is_fixed[mesh.tets].any(axis=1)


def _one_sided_poly(d_ref: float, E0: float, tension, compression):
    """Python correction adding E0 * d_ref * sum_k c_k (d/d_ref)^(k+2) per principal stress on
    each side, with its exact diagonal Jacobian."""
    ct = np.asarray(tension, float)
    cc = np.asarray(compression, float)

    def fn(Fh, Fhdot):
        Fh = np.asarray(Fh)
        dP = np.zeros_like(Fh)
        dd = np.zeros_like(Fh)
        for coeffs, side in ((ct, 1.0), (cc, -1.0)):
            if not np.any(coeffs):
                continue
            d = np.clip(side * (Fh - 1.0), 0.0, None) / d_ref  # >= 0 on the active side
            for k, c in enumerate(coeffs):
                p = k + 2
                # stress pushes back on the active side: sign follows the strain's sign
                dP += side * c * E0 * d_ref * d**p
                dd += c * E0 * p * d ** (p - 1)
        J = np.zeros(Fh.shape + (3,))
        idx = np.arange(3)
        J[:, idx, idx] = dd
        return dP, J, None, None

    return _core.correction.PythonCorrection(fn)


def build_model(ctx: EffectContext, params: dict):
    """The C++ model with the families in `params` ({name: theta}) applied to the nominal one."""
    unknown = set(params) - set(FAMILIES) - {NUISANCE}
    if unknown:
        raise ValueError(f"unknown effect families {sorted(unknown)}")
    m = ctx.mesh.num_tets
    mat = ctx.material
    E = np.broadcast_to(np.asarray(mat.youngs_modulus, float), (m,)).copy()
    nu = np.broadcast_to(np.asarray(mat.poisson_ratio, float), (m,)).copy()
    rho = np.broadcast_to(np.asarray(mat.density, float), (m,)).copy()
    E0 = float(np.median(E))
    tension = compression = ()

    def th(name):
        return np.asarray(params[name], float)

    if "stiffness_scale" in params:
        E *= np.exp(np.clip(th("stiffness_scale")[0], -3, 3))
    if NUISANCE in params:
        lo, hi = ctx.offset_range
        E *= np.exp(np.clip(th(NUISANCE)[0], lo - ctx.offset_applied, hi - ctx.offset_applied))
    if "heterogeneity" in params and ctx.region is not None:
        t = th("heterogeneity")
        E[ctx.region] *= np.exp(np.clip(t[0], -4, 4))
        if len(t) > 1:
            E[~ctx.region] *= np.exp(np.clip(t[1], -4, 4))
    if "support_compliance" in params:
        E[ctx.clamp_layer] *= np.exp(np.clip(th("support_compliance")[0], -5, 3))
    if "poisson_ratio" in params:
        nu = np.clip(nu + 0.1 * th("poisson_ratio")[0], 0.0, 0.49)
    if "density" in params:
        rho *= np.exp(np.clip(th("density")[0], -3, 3))
    damping = damping_of(ctx, params)
    if "tension_nonlinearity" in params:
        tension = th("tension_nonlinearity")
    if "compression_nonlinearity" in params:
        compression = th("compression_nonlinearity")

    material = Material(mat.model, E, nu, rho, list(mat.edits))
    correction = None
    if len(tension) or len(compression):
        correction = _one_sided_poly(ctx.d_ref, E0, tension, compression)
    return make_model(ctx.mesh, material, damping, correction)


def damping_of(ctx: EffectContext, params: dict) -> Damping:
    """The damping of the model `build_model(ctx, params)`: the nominal Rayleigh coefficients
    moved by the damping families (alpha_M by theta 0.1 omega, alpha_K by theta 0.1 / omega, the
    alpha_K polynomial of s1 by theta 0.1 / omega / d_ref^k), clamped at 0."""
    dmp = ctx.damping
    aM, aK = float(dmp.alpha_mass), float(dmp.alpha_stiffness)
    kpoly = list(dmp.stiffness_poly)
    for name in ("rayleigh_damping", "strain_dependent_damping"):
        if name not in params:
            continue
        t = np.asarray(params[name], float)
        aM = max(aM + t[0] * 0.1 * ctx.omega, 0.0)
        aK = max(aK + t[1] * 0.1 / ctx.omega, 0.0)
        if name == "strain_dependent_damping":
            kpoly = list(kpoly) + [0.0] * max(0, 2 - len(kpoly))
            for k in range(2):
                kpoly[k] += t[k + 2] * 0.1 / ctx.omega / ctx.d_ref ** (k + 1)
    return Damping(aM, aK, list(dmp.mass_poly), kpoly)


# unit steps of the damping coordinates (damping_coordinates): alpha_M and alpha_K, each moved as
# the damping families' theta = 1 moves it
DAMPING_STEPS = ({"rayleigh_damping": [1.0, 0.0]}, {"rayleigh_damping": [0.0, 1.0]})


def damping_coordinates(ctx: EffectContext, params: dict) -> np.ndarray:
    """(2,) how far the Rayleigh coefficients of `params` lie from the nominal ones in the units
    of DAMPING_STEPS (the clamps at 0 included): alpha_M, alpha_K. (The strain-dependent
    family's alpha_K polynomial is not a coordinate: the discrepancy does not follow it,
    discretisation.discretisation.)"""
    if "rayleigh_damping" not in params and "strain_dependent_damping" not in params:
        return np.zeros(2)
    d0, d = ctx.damping, damping_of(ctx, params)
    return np.array([(d.alpha_mass - d0.alpha_mass) / (0.1 * ctx.omega),
                     (d.alpha_stiffness - d0.alpha_stiffness) / (0.1 / ctx.omega)])


def describe(name: str, theta, ctx: EffectContext) -> dict:
    """Physical parameter values of a fitted family, for diagnosis.json."""
    t = np.asarray(theta, float)
    if name in ("stiffness_scale", "density"):
        # relative to a model as fine as the once-refined mesh; the range spans truths from
        # 1.5x finer than the model to the continuum
        sign = 1.0 if name == "stiffness_scale" else -1.0
        tot = t[0] + sign * ctx.offset_applied
        lo, hi = ctx.offset_range
        return {"scale": float(np.exp(tot - sign * ctx.offset_reference)),
                "scale_range": sorted([float(np.exp(tot - sign * lo)), float(np.exp(tot - sign * hi))]),
                "scale_on_model_mesh": float(np.exp(tot))}
    if name == "heterogeneity":
        return {"scale": float(np.exp(t[0] - t[1])), "region_scale": float(np.exp(t[0])),
                "rest_scale": float(np.exp(t[1])),
                "region_tets": int(ctx.region.sum()) if ctx.region is not None else 0}
    if name == "support_compliance":
        return {"scale": float(np.exp(t[0]))}
    if name == "poisson_ratio":
        nu0 = float(np.median(np.asarray(ctx.material.poisson_ratio, float)))
        return {"poisson_ratio": float(np.clip(nu0 + 0.1 * t[0], 0, 0.49)), "nominal": nu0}
    if name == "rayleigh_damping":
        return {
            "alpha_mass": max(ctx.damping.alpha_mass + t[0] * 0.1 * ctx.omega, 0.0),
            "alpha_stiffness": max(ctx.damping.alpha_stiffness + t[1] * 0.1 / ctx.omega, 0.0),
        }
    if name == "strain_dependent_damping":
        out = {"alpha_mass": max(ctx.damping.alpha_mass + t[0] * 0.1 * ctx.omega, 0.0),
               "alpha_stiffness": max(ctx.damping.alpha_stiffness + t[1] * 0.1 / ctx.omega, 0.0)}
        out.update({f"alpha_stiffness_c{k + 1}": float(t[k + 2] * 0.1 / ctx.omega / ctx.d_ref ** (k + 1))
                    for k in range(2)})
        return out
    if name in ("tension_nonlinearity", "compression_nonlinearity"):
        E0 = float(np.median(np.asarray(ctx.material.youngs_modulus, float)))
        # stress added at a strain of d_ref, relative to the nominal E0 * d_ref
        return {"c2": float(t[0]), "c3": float(t[1]), "strain_ref": ctx.d_ref,
                "stress_at_strain_ref_Pa": float(E0 * ctx.d_ref * (t[0] + t[1]))}
    return {f"theta{i}": float(v) for i, v in enumerate(t)}
