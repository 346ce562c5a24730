"""Material and damping descriptions (SI units) and their conversion to a C++ model."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import _core

MODELS = ("corotated", "neo_hookean", "stvk", "designed")


def _show(value) -> str:
    """A scalar as itself; a per-tet array by its offending range."""
    a = np.asarray(value, float)
    return repr(float(a)) if a.ndim == 0 else f"values in [{a.min():.4g}, {a.max():.4g}] ({a.size} tets)"


@dataclass
class Material:
    """An elastic law with Young's modulus E (Pa), Poisson ratio nu and density (kg/m^3).

    Each of E, nu, density may be a scalar or a per-tet array (heterogeneous objects).
    `edits` (designed material only): (amplitude Pa, centre stretch, half-width) bumps added to
    each principal stress on top of neo-Hookean, in a tension (centre > 1) or compression range.
    """

    model: str = "corotated"
    youngs_modulus: float | np.ndarray = 1e5
    poisson_ratio: float | np.ndarray = 0.4
    density: float | np.ndarray = 1000.0
    edits: list = field(default_factory=list)

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"unknown material model {self.model!r}; expected one of {MODELS}")
        nu = np.asarray(self.poisson_ratio, float)
        if np.any(nu < 0) or np.any(nu >= 0.5):
            raise ValueError(f"poisson_ratio must lie in [0, 0.5), got {_show(self.poisson_ratio)}")
        if np.any(np.asarray(self.youngs_modulus, float) <= 0):
            raise ValueError(f"youngs_modulus must be > 0 (Pa), got {_show(self.youngs_modulus)}")
        if np.any(np.asarray(self.density, float) <= 0):
            raise ValueError(f"density must be > 0 (kg/m^3), got {_show(self.density)}")

    def lame(self, num_tets: int):
        E = np.broadcast_to(np.asarray(self.youngs_modulus, float), (num_tets,)).copy()
        nu = np.broadcast_to(np.asarray(self.poisson_ratio, float), (num_tets,)).copy()
        return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


@dataclass
class Damping:
    """Rayleigh damping force -(alpha_mass M + alpha_stiffness K) v, alpha_mass in 1/s and
    alpha_stiffness in s; each optionally a polynomial of the element's largest principal
    stretch s1: alpha(s1) = alpha + sum_k c_k (s1 - 1)^k (k = 1, 2, ...), clamped at 0."""

    alpha_mass: float = 0.0
    alpha_stiffness: float = 0.0
    mass_poly: list = field(default_factory=list)
    stiffness_poly: list = field(default_factory=list)

    def __post_init__(self):
        if self.alpha_mass < 0 or self.alpha_stiffness < 0:
            raise ValueError(f"Rayleigh coefficients must be >= 0, got alpha_mass {self.alpha_mass} (1/s), "
                             f"alpha_stiffness {self.alpha_stiffness} (s)")


def make_model(mesh, material: Material, damping: Damping | None = None, correction=None):
    """Build the C++ model (mesh + material + damping + optional correction)."""
    damping = damping or Damping()
    m = mesh.num_tets
    mu, lam = material.lame(m)
    rho = np.broadcast_to(np.asarray(material.density, float), (m,)).copy()
    model = _core.fem.Model(
        mesh,
        material.model,
        mu,
        lam,
        rho,
        edits=[tuple(map(float, e)) for e in material.edits],
        alpha_mass=float(damping.alpha_mass),
        alpha_stiffness=float(damping.alpha_stiffness),
        mass_poly=[float(c) for c in damping.mass_poly],
        stiffness_poly=[float(c) for c in damping.stiffness_poly],
    )
    if correction is not None:
        model.correction = correction
    return model
