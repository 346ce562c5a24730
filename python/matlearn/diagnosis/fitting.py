"""Fitting effect families to the recordings, and ranking them.

1. Sensitivities: one finite-difference simulation per parameter of every family (and per
   spatial patch for the located heterogeneity) around the nominal model gives the Jacobian J of
   the train-marker residual. A family's cheap fit is the linear least-squares step on its
   columns (what the residual says it should be), with the residual explained predicted.
2. Refinement: Levenberg-Marquardt on the simulated residual from the cheap fit, a few
   evaluations (each one forward simulation per train recording).
3. Ranking: a BIC-like score on the residual plus the error floor (noise + discretisation), so no
   family gains by explaining what is below the floor; parameters counted with a located region
   as one more.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .effects import FAMILIES, build_model


@dataclass
class Fit:
    name: str  # family name, or "a+b" for combinations
    params: dict  # {family: theta}
    rss: float
    dof: int
    evaluations: int = 0
    history: list = field(default_factory=list)


def residual_of(problem, ctx, params: dict, recs=None) -> np.ndarray:
    return problem.residual(build_model(ctx, params), recs)



def sensitivities(problem, ctx, r0, names, step=0.1, progress=None):
    """{family: (J (N x k), thetas)} by forward differences around theta = 0."""
    out = {}
    for name in names:
        k = len(FAMILIES[name].parameters)
        J = np.zeros((len(r0), k))
        for i in range(k):
            th = np.zeros(k)
            th[i] = step
            J[:, i] = (residual_of(problem, ctx, {name: th}) - r0) / step
            if progress:
                progress(f"sensitivity {name}[{i}]")
        out[name] = J
    return out


def linear_fit(J: np.ndarray, r0: np.ndarray, max_step: float = 3.0):
    """theta minimising |r0 + J theta| (ridge-stabilised, step-limited), predicted rss."""
    JTJ = J.T @ J
    lam = 1e-6 * np.trace(JTJ) / max(len(JTJ), 1) + 1e-300
    th = -np.linalg.solve(JTJ + lam * np.eye(len(JTJ)), J.T @ r0)
    nrm = np.abs(th).max() if len(th) else 0.0
    if nrm > max_step:
        th *= max_step / nrm
    r = r0 + J @ th
    return th, float(r @ r)


def refine(problem, ctx, names: list, theta0: dict, r_start=None, iterations=3, step=0.07,
           progress=None, target=None, recs=None, r_zero=None) -> Fit:
    """Levenberg-Marquardt over the joint parameters of `names` on simulated residuals (minus
    `target`, a residual vector to match instead of the observations, if given)."""
    def res(params):
        r = residual_of(problem, ctx, params, recs)
        return r if target is None else r - target

    sizes = [len(FAMILIES[n].parameters) for n in names]
    split = np.cumsum(sizes)[:-1]

    def unpack(v):
        return {n: p for n, p in zip(names, np.split(v, split))}

    x = np.concatenate([np.asarray(theta0.get(n, np.zeros(s)), float) for n, s in zip(names, sizes)])
    r = res(unpack(x)) if r_start is None else r_start
    evals = 0 if r_start is not None else 1
    cost = float(r @ r)
    if r_zero is not None and cost > float(r_zero @ r_zero):
        # the cheap (linearised) start is worse than the baseline: start from the baseline
        x, r, cost = np.zeros_like(x), r_zero, float(r_zero @ r_zero)
    hist = [cost]
    mu = 1e-3
    for it in range(iterations):
        J = np.zeros((len(r), len(x)))
        for i in range(len(x)):
            xp = x.copy()
            xp[i] += step
            J[:, i] = (res(unpack(xp)) - r) / step
            evals += 1
        JTJ, g = J.T @ J, J.T @ r
        improved = False
        for _ in range(2):
            A = JTJ + mu * np.diag(np.diag(JTJ) + 1e-12 * np.trace(JTJ) + 1e-300)
            dx = -np.linalg.solve(A, g)
            if np.abs(dx).max() > 2.0:
                dx *= 2.0 / np.abs(dx).max()
            rn = res(unpack(x + dx))
            evals += 1
            cn = float(rn @ rn)
            if cn < cost:
                x, r, cost = x + dx, rn, cn
                mu = max(mu / 10, 1e-6)
                improved = True
                break
            mu *= 10
        hist.append(cost)
        if progress:
            progress(f"refine {'+'.join(names)} it {it + 1}: rss {cost:.3e}")
        if not improved or (len(hist) > 2 and hist[-2] - cost < 0.01 * hist[-2]):
            break
    dof = sum(sizes) + sum(FAMILIES[n].extra_dof for n in names)
    return Fit("+".join(names), unpack(x), cost, dof, evals, hist)


def scan(problem, ctx, name: str, theta_cheap, r0, grid=(-0.6, -0.3, 0.3, 0.6)) -> np.ndarray:
    """Best of the linearised estimate and a coarse grid of a 1-parameter family (simulated),
    as the start of the local refinement."""
    best = (float(r0 @ r0), np.zeros(1))
    for t in [float(np.asarray(theta_cheap).ravel()[0])] + list(grid):
        r = residual_of(problem, ctx, {name: [t]})
        c = float(r @ r)
        if c < best[0]:
            best = (c, np.array([t]))
    return best[1]


def score(rss: float, dof: int, n_eff: float, rss_floor: float) -> float:
    """BIC on the residual above the floor: n log((rss + floor) / n) + dof log n (lower = better)."""
    n = max(n_eff, 2.0)
    return float(n * np.log((rss + rss_floor) / n + 1e-300) + dof * np.log(n))


def locate_region(J_patches: np.ndarray, r0: np.ndarray, allowed=None):
    """Per-patch log-stiffness change (ridge least squares on the patch sensitivities) and the
    region: patches deviating from the median change by more than half the largest deviation,
    on the side of the largest deviation (the median absorbs a uniform offset of the baseline).
    `allowed`: bool per column that may belong to the region (default all).
    Returns (region mask over columns, per-column change)."""
    n = J_patches.shape[1]
    allowed = np.ones(n, bool) if allowed is None else np.asarray(allowed, bool)
    JTJ = J_patches.T @ J_patches
    lam = 0.05 * np.trace(JTJ) / max(len(JTJ), 1)
    th = -np.linalg.solve(JTJ + lam * np.eye(len(JTJ)), J_patches.T @ r0)
    dev = th - np.median(th)
    dev[~allowed] = 0.0
    i = int(np.argmax(np.abs(dev)))
    sel = allowed & (np.sign(dev) == np.sign(dev[i])) & (np.abs(dev) >= 0.5 * np.abs(dev[i]))
    return sel, th


def make_patches(mesh, count: int, seed: int = 0) -> np.ndarray:
    """Spatial patches: k-means of element centroids (volume-weighted), labels (#T,)."""
    from sklearn.cluster import KMeans

    C = np.asarray(mesh.vertices)[np.asarray(mesh.tets)].mean(axis=1)
    count = int(min(count, len(C)))
    km = KMeans(count, n_init=4, random_state=seed).fit(C, sample_weight=np.asarray(mesh.rest_volumes))
    return km.labels_
