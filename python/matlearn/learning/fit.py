"""From control forces to a material correction (method.md section 6).

The correction is an RBF model over principal stretches Fh (RbfCorrection in C++):

    dPh(Fh)    = A (Fh - 1) + b + sum_k w_k phi_k(Fh),   phi_k(Fh) = sqrt(|Fh - c_k|^2 + eps^2)
    dalpha(Fh) = a0 + sum_k wa_k phi_k(Fh)                 (change of the stiffness-damping alpha_K)

Centres c_k come from k-means over the principal stretches of all elements and frames.
Extrapolation: the RBF part is only trusted in the box of the centres widened by eps
(`RbfParams.box`, about the hull of the fitted stretches); outside it every elastic kernel is
replaced by its first-order extension from the nearest box point (`rbf_kernel`), so beyond the
training stretches the correction continues linearly with its slope at the edge of the data
(continuous, growth at most linear, no runaway of the kernels' far field); the damping kernels
are held at their box value (constant alpha change). The bias
is tied to the weights, b = -sum_k w_k phi_k(1), so the rest shape stays stress-free (the truth
and the nominal law are both stress-free at rest). Damping is passive by construction: the C++
model clamps alpha_K + dalpha at 0 per element.

Fit. Over frames j (positions x_j, velocities v_j, control forces fc_j) the new total correction
must produce the current correction's force plus the control force:

    B_j dPh_new(Fh_j) + G_j dalpha_new(Fh_j) = fc_j + f_corr,current(x_j, v_j)

with B_j the force map and G_j the stiffness-damping map (column e = -K_e v_e). Both sides are
projected on the space-time basis (Phi^T ...): the space-time solve determines only the reduced
forces; the component of fc orthogonal to span(M Phi) is the elastic response to the basis
truncation, not a material error, and fitting it would learn the truncation. The problem is
linear in (w, A, wa, a0): one regularised least-squares solve over all frames; the normal
equations are accumulated over all frames of a recording in one C++ call
(`_core.fit.normal_equations`, cpp/learning/fit_normal_equations.cpp).

Regularisation (`smooth`): the fit minimises

    |D theta - y|^2 + smooth |y|^2 mean_i |J_rbf(s_i)|_F^2 / M^2    (+ a tiny numerical ridge)

with J_rbf(s) = sum_k w_k grad g_k(s)^T the tangent of the RBF part at the fitted stretch
samples s_i and M = 2 mu + lam the nominal P-wave modulus: a nonlinear stress correction whose
tangent is a fraction t of the nominal stiffness costs smooth t^2 of the whole target energy.
The linear part A (a global change of the moduli) is not penalised by `smooth` (see `linear`
below). Why the RBF part is: the stretches of a
recording span a few percent, the k-means centres are ~eps apart and the multiquadric kernels
are nearly collinear there, so without it the normal matrix is numerically singular and the
tiny column-scaled ridge left weights of ~1e6 Pa whose cancelling tangents exceeded the nominal
modulus: inside the fitted range it reproduced the training forces, but just beyond it (a
larger held-out motion, the C1 extension continues with the edge slope) the total tangent
turned negative and the simulation blew up (tests/python/test_learn_clouds.py: held-out 337 %
of the object size after a second iteration; a 1e-14 relative change of the weights moved it
by 5 %, i.e. chaotic, which is why two runs differing only in round-off gave 0.98 % and 337 %).
The loop (`LearnOptions.smoothing`) picks the weight among a few candidates by the forward
*train* error.

Extrapolation penalties (`linear`, `edge`; candidates `EXTRAPOLATION_WEIGHTS`): the same
tangent penalty on the linear part A (linear |y|^2 |A|_F^2 / M^2) and on the RBF part's slope at
the points where a motion twice the fitted one leaves the centres' box (edge |y|^2 mean
|J_rbf(edge)|^2 / M^2, `FitSystem.edge_penalty`: the slope the C1 extension continues with).
Both act only where the data are silent. Where the recordings do not fix the stress scale, A runs
along that near-null direction: on the displacement-driven tension sphere (bench/learning_table.py,
cap keyframed, quasi-static) the free fits removed 60-100 % of the nominal P-wave modulus (A/M
about -0.8 on the diagonal, -0.6 off it), and without the guard every one of them would have
raised the forward train error from 1.55 % to 2.4-3.4 %. With A penalised (weight 1) the same control
forces give 1.19-1.31 %, but the RBF then meets the truth's softening bump (negative tangent at
stretch 1.14-1.2) at the box edge and its extension softens without end (tangent margin -0.2:
rejected); with the edge slope penalised too (weight 10) the margin is +0.03..0.07 and the train
error 1.21-1.29 %. The softening inside the data stays allowed (tangent_margin checks only beyond
the box). Where the modulus is wrong and identified (the turtle: -43 % of E) a penalised A would
be biased towards no change, so the free and the penalised family are both candidates and the
forward train error chooses.

Symmetric fit (`symmetric`, LearnOptions.symmetric). A stress correction must be an isotropic
function of F: dPh(Q s) = Q dPh(s) for every permutation Q of the principal axes (then dPh_i =
dPh_j wherever s_i = s_j, and U diag(Ph) V^T does not depend on the arbitrary frame there). A free
fit is not (the table's sphere_compression RBF: stresses 0.8-1.7 kPa apart at coincident
stretches; Newton then cycles at the force jump: 163/206 of 300 test steps at the iteration
limit, 872/1077 factorisations). The symmetric fit makes it so by construction: k-means runs on
the sorted stretches; every centre r_k (an orbit representative) is expanded to its 6
permutations P_j r_k with tied weights P_j v_k, the linear part is alpha I + beta 1 1^T and the
damping weight is one per orbit (symmetric_expansion; 3c + 2 (+ c + 1) unknowns for 6c centres),
and the box is the same on every axis (a permutation of a clamped point is the clamped
permutation). Then dPh(Q s) = Q dPh(s) and dalpha(Q s) = dalpha(s) exactly (to round-off,
tests/python/test_fit_symmetric.py), and the blend of RBF_ISOTROPIC_WIDTH is not needed (the
re-learned sphere_compression: 43/38 steps at the limit, 25/41 factorisations). The
normal equations are assembled for the 6c centres and reduced, T^T N T. Cost: 6x the kernels per
element in every force evaluation (cpp/correction evaluates them as vectorised columns).

Tangent damping (`tangent_damping`, LearnOptions.tangent_damping, off by default). Rayleigh damping
alpha_K K on a corrected material can use the nominal tangent (the default: (alpha_K + dalpha)
K_psd(nominal)) or the corrected one, (alpha_K + dalpha) K_psd(nominal + correction), as a truth
whose own tangent is edited does (the learning table's spheres). The latter is bilinear in the
elastic and damping weights and the PSD projection is not linear; the normal equations
(cpp/learning/fit_normal_equations.cpp) linearise it at the current model: the elastic features
damp with the current alpha_K + dalpha through the derivative of the projection at the current
total tangent, the damping columns act on the current corrected tangent, and the data lose the
difference, so the design equals the model's force at the current weights and errs to second
order around them (tests/python/test_tangent_damping.py). Measured on the spheres (docs/results.md).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from .. import _core


# (linear, edge) extrapolation-penalty candidates per smoothing weight: free, and penalised
# (module docstring; LearnOptions.extrapolation)
EXTRAPOLATION_WEIGHTS = ((0.0, 0.0), (1.0, 10.0))
# RbfCorrection isotropic_width of every correction built from RbfParams (the blend at coincident
# stretches, cpp/correction/isotropy.hpp; < 0: 0.1 x the centres' std); 0: off (the default)
RBF_ISOTROPIC_WIDTH = 0.0
# the 6 permutations pi of the three principal axes (symmetric fits: module docstring)
PERMUTATIONS = np.array(list(itertools.permutations(range(3))))


@dataclass
class RbfParams:
    """Parameters of an RbfCorrection (see module docstring); shapes (c,3), (c,3), (3,3), (3,),
    (c,) or (0,), scalar, scalar; clamp: clamp the kernel input to `box()` (False for models
    saved before the clamp existed); tangent_damping: the stiffness-proportional Rayleigh
    damping acts on the corrected tangent (`_core` Correction.tangent_damping; False for models
    saved before it existed)."""

    centers: np.ndarray
    weights: np.ndarray
    linear: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    alpha_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    alpha_bias: float = 0.0
    epsilon: float = 0.05
    clamp: bool = True
    tangent_damping: bool = False

    def box(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(lower, upper) (3,) each: the centres' bounding box widened by epsilon, or
        (None, None) without clamping."""
        return centers_box(self.centers, self.epsilon) if self.clamp else (None, None)

    def correction(self):
        lo, hi = self.box()
        c = _core.correction.RbfCorrection(
            np.ascontiguousarray(self.centers, float), np.ascontiguousarray(self.weights, float),
            np.asarray(self.linear, float), np.asarray(self.bias, float),
            np.asarray(self.alpha_weights, float), float(self.alpha_bias), float(self.epsilon),
            lower=lo, upper=hi, isotropic_width=RBF_ISOTROPIC_WIDTH)
        c.tangent_damping = bool(self.tangent_damping)
        return c

    def to_arrays(self, prefix: str = "rbf_") -> dict:
        return {prefix + k: np.asarray(getattr(self, k), float) for k in
                ("centers", "weights", "linear", "bias", "alpha_weights", "alpha_bias", "epsilon",
                 "clamp", "tangent_damping")}

    @classmethod
    def from_arrays(cls, d, prefix: str = "rbf_") -> "RbfParams":
        keys = d.files if hasattr(d, "files") else d.keys()
        return cls(**{k: np.asarray(d[prefix + k], float) for k in
                      ("centers", "weights", "linear", "bias", "alpha_weights")},
                   alpha_bias=float(np.asarray(d[prefix + "alpha_bias"])),
                   epsilon=float(np.asarray(d[prefix + "epsilon"])),
                   clamp=bool(np.asarray(d[prefix + "clamp"])) if prefix + "clamp" in keys else False,
                   tangent_damping=(bool(np.asarray(d[prefix + "tangent_damping"]))
                                    if prefix + "tangent_damping" in keys else False))


def centers_box(centers: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box of the centres (c, 3) widened by eps on every side: where the RBF part of a
    correction is trusted (k-means centres lie inside the hull of the fitted stretches)."""
    C = np.asarray(centers, float)
    return C.min(axis=0) - eps, C.max(axis=0) + eps


def rbf_kernel(Fh: np.ndarray, centers: np.ndarray, eps: float, box=(None, None),
               damping: bool = False) -> np.ndarray:
    """Elastic kernels (m, c): phi_k(Fh) = sqrt(|Fh - c_k|^2 + eps^2) inside box = (lower,
    upper) (or everywhere for Nones); outside, the first-order extension from the nearest box
    point sc, phi_k(sc) + (sc - c_k).(Fh - sc) / phi_k(sc). damping: the damping kernels
    phi_k(sc) instead (constant beyond the box)."""
    Fh = np.asarray(Fh, float)
    sc = np.clip(Fh, box[0], box[1]) if box[0] is not None else Fh
    d = sc[:, None, :] - centers[None]
    phi = np.sqrt((d ** 2).sum(-1) + eps * eps)
    if damping:
        return phi
    return phi + (d * (Fh - sc)[:, None, :]).sum(-1) / phi


def choose_centers(Fh_samples: np.ndarray, num_centers: int, seed: int = 0,
                   max_samples: int = 20000) -> tuple[np.ndarray, float]:
    """k-means centres (c, 3) over principal-stretch samples (k, 3) and the kernel width eps
    (the median distance from a centre to its nearest other centre, at least 1e-3)."""
    from sklearn.cluster import KMeans

    S = np.asarray(Fh_samples, float)
    if S.ndim != 2 or S.shape[1] != 3 or len(S) == 0:
        raise ValueError(f"Fh_samples: expected shape (k, 3) with k > 0, got {S.shape}")
    rng = np.random.default_rng(seed)
    if len(S) > max_samples:
        S = S[rng.choice(len(S), max_samples, replace=False)]
    c = int(min(num_centers, len(np.unique(np.round(S, 9), axis=0))))
    km = KMeans(n_clusters=c, n_init=4, random_state=seed).fit(S)
    C = km.cluster_centers_
    if c > 1:
        d = np.sqrt(((C[:, None] - C[None]) ** 2).sum(-1))
        np.fill_diagonal(d, np.inf)
        eps = float(max(np.median(d.min(axis=1)), 1e-3))
    else:
        eps = float(max(S.std(), 1e-3))
    return C, eps


def orbit_representatives(centers: np.ndarray) -> np.ndarray:
    """One representative per orbit of the axis permutations: every centre's coordinates sorted
    descending, duplicates removed, rows in lexicographic order (so that
    orbit_representatives(symmetric_expansion(R)[0]) == orbit_representatives(R))."""
    return np.unique(-np.sort(-np.asarray(centers, float), axis=1), axis=0)


def symmetric_expansion(reps: np.ndarray, damping: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The permutation-equivariant RBF (module docstring, `symmetric`) on orbit representatives
    reps (c, 3). Returns (centres (6c, 3), T (p_full, p_sym)): row 6k + j of the centres is P_j
    r_k, (P_j r)_i = r[pi_j(i)] for the permutations pi_j of PERMUTATIONS, and T maps the
    symmetric parameters theta_sym = [V (c, 3) row-major, alpha, beta, (u (c), a0 with damping)]
    to fit_system's parameter vector of those centres (per stress component a: [w (6c), A row
    a (3)], then [wa (6c), a0]): w_{6k+j} = P_j V_k, A = alpha I + beta 1 1^T, wa_{6k+j} = u_k.
    Then dPh(Q s) = Q dPh(s) and dalpha(Q s) = dalpha(s) for every permutation Q."""
    R = np.asarray(reps, float)
    c = len(R)
    C = R[:, PERMUTATIONS].reshape(6 * c, 3)
    cf = 6 * c
    pf = 3 * (cf + 3) + ((cf + 1) if damping else 0)
    ps = 3 * c + 2 + ((c + 1) if damping else 0)
    T = np.zeros((pf, ps))
    k, j, a = np.meshgrid(np.arange(c), np.arange(6), np.arange(3), indexing="ij")
    T[(a * (cf + 3) + 6 * k + j).ravel(), (3 * k + PERMUTATIONS[j, a]).ravel()] = 1.0
    for a in range(3):
        T[a * (cf + 3) + cf + a, 3 * c] = 1.0
        T[a * (cf + 3) + cf: (a + 1) * (cf + 3), 3 * c + 1] = 1.0
    if damping:
        T[3 * (cf + 3) + np.arange(cf), 3 * c + 2 + np.arange(cf) // 6] = 1.0
        T[3 * (cf + 3) + cf, 3 * c + 2 + c] = 1.0
    return C, T


@dataclass
class FitFrames:
    """Frames to fit from: positions X (F, n, 3), velocities V (F, n, 3), control forces
    fc (F, n, 3) and the basis phi (3n, r) the forces are projected on (None: full space, with
    the rows of `constrained` vertices dropped)."""

    X: np.ndarray
    V: np.ndarray
    fc: np.ndarray
    phi: np.ndarray | None = None
    constrained: np.ndarray | None = None


def correction_force(model_corr, model_nom, x, v) -> np.ndarray:
    """Force (3n) the current correction adds at (x, v) (elastic + damping)."""
    return (np.asarray(model_corr.forces(x, v)) - np.asarray(model_nom.forces(x, v))).ravel()


def kernel_gradients(S: np.ndarray, centers: np.ndarray, eps: float, box=(None, None)) -> np.ndarray:
    """Gradients (k, c, 3) of the elastic kernels (rbf_kernel, with its box extension) at
    stretches S (k, 3); the same formula as extended_kernel in cpp/correction."""
    S = np.asarray(S, float)
    sc = np.clip(S, box[0], box[1]) if box[0] is not None else S
    d = sc[:, None, :] - centers[None]
    phi = np.sqrt((d ** 2).sum(-1) + eps * eps)
    g = d / phi[..., None]
    inside = (S == sc)[:, None, :]
    dd = (d * (S - sc)[:, None, :]).sum(-1)
    return np.where(inside, g * (1.0 - dd / phi**2)[..., None], g)


@dataclass
class FitSystem:
    """The assembled least-squares problem of a correction fit: the normal equations (N, rhs,
    yy = |y|^2) over all frames for fixed centres, and what the regularised solves need. One
    system serves every (ridge, smooth) candidate of an iteration (:func:`solve_fit`)."""

    N: np.ndarray
    rhs: np.ndarray
    yy: float
    count: int
    centers: np.ndarray
    epsilon: float
    box: tuple
    clamp: bool
    damping: bool
    samples: np.ndarray
    modulus: float
    seed: int
    max_penalty_samples: int
    transform: np.ndarray | None = None
    tangent_damping: bool = False
    _penalty: np.ndarray | None = None
    _edge: np.ndarray | None = None

    def _penalty_samples(self) -> np.ndarray:
        """The fitted stretches, subsampled (seeded) to at most max_penalty_samples."""
        S = self.samples
        if len(S) > self.max_penalty_samples:
            S = S[np.random.default_rng(self.seed).choice(len(S), self.max_penalty_samples, replace=False)]
        return S

    def _gradient_gram(self, points) -> np.ndarray:
        """(c, c) mean over `points` of grad g_k . grad g_l."""
        G = kernel_gradients(points, self.centers, self.epsilon, self.box)
        # one BLAS product (c, 3k) x (3k, c): 17-37x faster than the equivalent einsum, whose
        # unoptimised loops took 11 % of the dragon's learning-table run (bench/learning_parallel.py)
        H = G.transpose(1, 0, 2).reshape(len(self.centers), -1)
        return (H @ H.T) / len(points)

    def penalty(self) -> np.ndarray:
        """Pk (c, c): mean over the (subsampled) fitted stretches of grad g_k . grad g_l, so that
        the mean squared tangent of the RBF part of one stress component is w^T Pk w (cached)."""
        if self._penalty is None:
            self._penalty = self._gradient_gram(self._penalty_samples())
        return self._penalty

    def edge_penalty(self) -> np.ndarray:
        """Pe (c, c): as `penalty`, at the points where a motion twice the fitted one
        (extension_probes) leaves the centres' box, i.e. of the slope with which the RBF part
        is extended beyond the data (zeros when nothing leaves the box; cached)."""
        if self._edge is None:
            c = len(self.centers)
            S = 1.0 + 2.0 * (self._penalty_samples() - 1.0)
            self._edge = np.zeros((c, c))
            if self.box[0] is not None:
                out = np.any((S < self.box[0]) | (S > self.box[1]), axis=1)
                if out.any():
                    self._edge = self._gradient_gram(np.clip(S[out], self.box[0], self.box[1]))
        return self._edge


def fit_system(nominal_model, frames: list, num_centers: int = 24, current_model=None,
               damping: bool = True, seed: int = 0, stride: int = 1, centers=None,
               clamp: bool = True, max_penalty_samples: int = 4000,
               symmetric: bool = False, tangent_damping: bool = False) -> FitSystem:
    """Assemble the fit's normal equations over all frames (one C++ call per recording) for
    the centres `centers` = (C, eps) or k-means centres of the fitted stretches (`seed`).
    symmetric: the permutation-equivariant RBF (module docstring): k-means over the sorted
    stretches, the centres (given or not) reduced to orbit representatives and expanded to
    their 6 permutations (symmetric_expansion), and the normal equations reduced to the
    symmetric parameters, T^T N T (`FitSystem.transform` = T). tangent_damping: fit a
    correction whose elastic part also enters the stiffness-proportional damping (module
    docstring, "Tangent damping"; current_model's correction must have it too).
    Arguments as :func:`fit_correction`."""
    if not frames:
        raise ValueError("fit_correction: no frames")
    if nominal_model is None:
        raise ValueError("fit_correction: nominal_model is None")
    samples = np.concatenate([np.asarray(_core.fit.principal_stretches(
        nominal_model, np.asarray(fr.X)[::stride])) for fr in frames])
    if centers is None:
        C, eps = choose_centers(-np.sort(-samples, axis=1) if symmetric else samples, num_centers, seed)
    else:
        C, eps = centers
    T = None
    if symmetric:
        C, T = symmetric_expansion(orbit_representatives(C), damping)
    C = np.ascontiguousarray(C, float)
    c = len(C)
    box = centers_box(C, eps) if clamp else (None, None)
    p = 3 * (c + 3) + ((c + 1) if damping else 0)
    N = np.zeros((p, p))
    rhs = np.zeros(p)
    yy = 0.0
    count = 0
    for fr in frames:
        n = fr.X.shape[1]
        free = None
        if fr.phi is None:
            free = np.ones(3 * n, bool)
            if fr.constrained is not None:
                free[(3 * np.asarray(fr.constrained)[:, None] + np.arange(3)).ravel()] = False
        Nf, rf, yf, cf = _core.fit.normal_equations(
            nominal_model, current_model, np.asarray(fr.X)[::stride], np.asarray(fr.V)[::stride],
            np.asarray(fr.fc)[::stride], fr.phi, free, C, eps, box[0], box[1], damping,
            tangent_damping)
        N += Nf
        rhs += rf
        yy += yf
        count += cf
    if T is not None:
        N, rhs = T.T @ N @ T, T.T @ rhs
    modulus = float(np.median(2 * np.asarray(nominal_model.mu) + np.asarray(nominal_model.lam)))
    return FitSystem(N, rhs, float(yy), int(count), C, float(eps), box, clamp, damping, samples,
                     modulus, seed, max_penalty_samples, T, bool(tangent_damping))


def solve_fit(system: FitSystem, ridge: float = 1e-6, smooth: float = 0.0,
              linear: float = 0.0, edge: float = 0.0) -> tuple[RbfParams, dict]:
    """The regularised least-squares solve of an assembled system (module docstring): ridge
    relative to the mean diagonal of the column-normalised normal matrix, smooth the weight of
    the tangent penalty of the RBF part, linear the same penalty on the linear part A (the
    correction's global tangent: linear |y|^2 |A|_F^2 / M^2; 0: A free). Returns (params, info)."""
    s = system
    C, eps, c = s.centers, s.epsilon, len(s.centers)
    N, rhs, yy = s.N, s.rhs, s.yy
    ne = 3 * (c + 3)
    p = len(rhs)
    T = s.transform
    scale = np.sqrt(np.maximum(np.diag(N), 1e-300))
    Ns = N / scale[:, None] / scale[None]
    reg = ridge * np.trace(Ns) / p
    if smooth > 0 or linear > 0 or edge > 0:
        pf = p if T is None else T.shape[0]
        Pen = np.zeros((pf, pf))
        for a in range(3):
            sl = slice(a * (c + 3), a * (c + 3) + c)
            if smooth > 0:
                Pen[sl, sl] = smooth * s.penalty()
            if edge > 0:
                Pen[sl, sl] += edge * s.edge_penalty()
            sa = slice(a * (c + 3) + c, (a + 1) * (c + 3))
            Pen[sa, sa] = linear * np.eye(3)
        Pen *= yy / s.modulus**2
        if T is not None:
            Pen = T.T @ Pen @ T
        Ns = Ns + Pen / scale[:, None] / scale[None]
    theta = np.linalg.solve(Ns + reg * np.eye(p), rhs / scale) / scale
    res2 = max(yy - 2 * theta @ rhs + theta @ N @ theta, 0.0)
    if T is not None:
        theta = T @ theta
    We = theta[:ne].reshape(3, c + 3)  # per stress component: [w (c), A row (3)]
    W = We[:, :c].T.copy()
    A = We[:, c:].copy()
    bias = -(W.T @ rbf_kernel(np.ones((1, 3)), C, eps, s.box)[0])
    if s.damping:
        wa, a0 = theta[ne:ne + c].copy(), float(theta[ne + c])
    else:
        wa, a0 = np.zeros(0), 0.0
    params = RbfParams(C, W, A, bias, wa, a0, eps, s.clamp, s.tangent_damping)
    info = {"residual_ratio": float(np.sqrt(res2 / yy)) if yy > 0 else 0.0, "frames": s.count,
            "parameters": p, "centers": c, "epsilon": eps, "smooth": smooth, "linear": linear,
            "edge": edge, "symmetric": T is not None}
    return params, info


def fit_correction(nominal_model, frames: list, num_centers: int = 24, current_model=None,
                   damping: bool = True, ridge: float = 1e-6, seed: int = 0, stride: int = 1,
                   centers=None, clamp: bool = True, smooth: float = 0.0,
                   max_penalty_samples: int = 4000, symmetric: bool = False) -> tuple[RbfParams, dict]:
    """Least-squares RBF correction from control forces (module docstring):
    :func:`fit_system` then :func:`solve_fit`.

    nominal_model: the model without correction; frames: list of FitFrames; current_model: the
    same model with the current correction (or None); damping: also fit the strain-dependent alpha_K change;
    ridge: Tikhonov weight relative to the mean diagonal of the (column-normalised) normal
    matrix; stride: use every stride-th frame; centers: (C, eps) to reuse instead of k-means;
    clamp: clamp the kernels to the centres' box (RbfParams.box); smooth: weight of the
    tangent penalty of the RBF part (module docstring; 0: none), evaluated on at most
    max_penalty_samples of the fitted stretches (drawn with `seed`); symmetric: fit the
    permutation-equivariant RBF (module docstring).
    Returns (params, info) with info = dict(residual_ratio, frames, parameters)."""
    system = fit_system(nominal_model, frames, num_centers, current_model, damping, seed, stride,
                        centers, clamp, max_penalty_samples, symmetric)
    return solve_fit(system, ridge, smooth)


def extension_probes(nominal_model, frames: list, factor: float = 2.0, max_samples: int = 4000,
                     seed: int = 0) -> np.ndarray:
    """Stretches (k, 3) of a motion `factor` times larger than the fitted one: 1 + factor (s - 1)
    for (at most max_samples of) the principal stretches s of the fit frames. Where they leave
    the centres' box the correction is extrapolated, and :func:`tangent_margin` checks it there."""
    S = np.concatenate([np.asarray(_core.fit.principal_stretches(nominal_model, np.asarray(fr.X)))
                        for fr in frames])
    if len(S) > max_samples:
        S = S[np.random.default_rng(seed).choice(len(S), max_samples, replace=False)]
    return 1.0 + factor * (S - 1.0)


def tangent_margin(params: RbfParams, material, mu: float, lam: float, probes: np.ndarray) -> float:
    """Smallest eigenvalue of the symmetric part of the total principal tangent (nominal law +
    correction) over the probe stretches that lie outside the centres' box, divided by the
    nominal P-wave modulus 2 mu + lam (+inf when no probe lies outside). Negative: beyond the
    data the corrected material softens into instability (a held-out motion larger than the
    training one would blow up), so the loop rejects such an update. Inside the box the data
    decide (an edited truth may itself soften there)."""
    lo, hi = params.box()
    S = np.asarray(probes, float)
    if lo is not None:
        S = S[np.any((S < lo) | (S > hi), axis=1)]
    if len(S) == 0:
        return float("inf")
    T = np.asarray(_core.fem.principal_stress_derivative(
        material.model, S, np.full(len(S), mu), np.full(len(S), lam),
        [tuple(map(float, e)) for e in material.edits]))
    J = np.asarray(params.correction().evaluate(S, np.zeros_like(S))[1])
    T = T + J
    ev = np.linalg.eigvalsh(0.5 * (T + np.transpose(T, (0, 2, 1))))
    return float(ev.min() / (2 * mu + lam))


def project_linear_part(params: RbfParams, material, mu: float, lam: float) -> RbfParams:
    """A copy whose linear part A is changed minimally (Frobenius norm) so that the symmetric
    part of the total principal tangent at rest, T_nominal(1) + A, is positive semi-definite:
    its negative eigenvalues are raised to ~zero (the PSD projection the core applies to dP/dF,
    applied to the learned global modulus change)."""
    T0 = np.asarray(_core.fem.principal_stress_derivative(
        material.model, np.ones((1, 3)), np.array([mu]), np.array([lam]),
        [tuple(map(float, e)) for e in material.edits]))[0]
    A = np.asarray(params.linear, float)
    S = 0.5 * (T0 + A + (T0 + A).T)
    w, V = np.linalg.eigh(S)
    from dataclasses import replace

    floor = 1e-6 * (2 * mu + lam)  # strictly positive after round-off
    return replace(params, linear=A + (V * np.maximum(floor - w, 0.0)) @ V.T)
