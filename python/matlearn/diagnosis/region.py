"""Refining a located stiffer or softer region with stiffness tangents (linearised.py) instead
of one simulation per boundary group.

* `boundary_moves`: coarse-to-fine refinement of a located region's boundary. The elements on
  either side of the boundary are grouped (k-means, ~`target_size` elements); the effect of
  moving each group to the other side is predicted from the tangent at the fitted two-stiffness
  model (one pass for all groups), the moves are combined greedily while the predicted residual
  drops, and the new region is accepted only when its two scales, refit by simulation, give a
  lower simulated residual (every accepted move is checked by simulation). Rounds stop when no
  move is predicted to help or the simulated residual no longer drops (or by < 1 %).
* `restart_scales`: a two-stiffness fit that stalled without contrast is restarted from the
  tangent Gauss-Newton step of its two scales.

The patches themselves (pipeline) keep their finite-difference secants (step 0.1 in log
stiffness): the per-patch estimates of weakly loaded patches are poorly determined, and on the
suite's heterogeneity cases the located region was better from the secants (IoU 0.48 / 0.62)
than from exact tangents (0.12 / 0.0) at the baseline, far from the fitted contrast.
"""
from __future__ import annotations

import numpy as np

from .linearised import stiffness_jacobian


def contrast(params: dict) -> float:
    """Log-stiffness contrast of the region against the rest in heterogeneity parameters
    [log region, log rest] (0 without a fit)."""
    t = np.asarray(params.get("heterogeneity", [0.0, 0.0]), float)
    return float(t[0] - (t[1] if len(t) > 1 else 0.0))


def restart_scales(problem, ctx, fit, refine_fn, progress=None):
    """A two-stiffness fit that ended without contrast (region scale = rest scale, e.g. a
    Levenberg-Marquardt run that started from the baseline because the linearised start
    overshot, and then stalled) has nothing to locate and explains nothing of its own: the
    Gauss-Newton step of the two scales from the tangents at the fit (two directions, one
    pass) is tried at full, half and quarter length by simulation, and the best is refined
    with refine_fn(params) -> Fit. Returns the better of the two fits."""
    from .fitting import Fit, linear_fit, residual_of

    t = np.asarray(fit.params["heterogeneity"], float)
    Dir = np.column_stack([ctx.region, ~ctx.region]).astype(float)
    r_h, J = stiffness_jacobian(problem, ctx, fit.params, Dir)
    step, _ = linear_fit(J, r_h, max_step=2.0)
    best = (float(r_h @ r_h), None)
    for f in (1.0, 0.5, 0.25):
        th = t + f * step
        r = residual_of(problem, ctx, {"heterogeneity": th})
        if float(r @ r) < best[0]:
            best = (float(r @ r), th)
    if best[1] is None:
        return fit
    cand = refine_fn({"heterogeneity": best[1]})
    if progress:
        progress(f"heterogeneity restarted from the tangent step: rss {fit.rss:.3e} -> {cand.rss:.3e}")
    if cand.rss < fit.rss:
        return Fit(fit.name, cand.params, cand.rss, fit.dof, fit.evaluations + cand.evaluations, fit.history)
    return fit


def boundary_groups(mesh, region, target_size: int, seed: int = 0) -> list:
    """Groups of elements adjacent to the other side of `region` (sharing a vertex), on both
    sides, each ~target_size elements (k-means of centroids)."""
    from sklearn.cluster import KMeans

    T = np.asarray(mesh.tets)
    C = np.asarray(mesh.vertices)[T].mean(axis=1)
    nv = mesh.num_vertices
    groups = []
    for side in (region, ~region):
        other = np.zeros(nv, bool)
        other[T[~side].ravel()] = True
        idx = np.flatnonzero(side & other[T].any(axis=1))
        if len(idx) == 0:
            continue
        k = int(max(1, min(len(idx), round(len(idx) / target_size))))
        lab = (KMeans(k, n_init=2, random_state=seed).fit(C[idx]).labels_ if k > 1
               else np.zeros(len(idx), int))
        groups += [idx[lab == j] for j in range(k) if np.any(lab == j)]
    return groups


def greedy_moves(r, D) -> list:
    """Indices of columns of D (predicted residual changes) added greedily to r while |r| drops."""
    cur, chosen = r.copy(), []
    G = D.T @ D
    while True:
        # |cur + d_i|^2 - |cur|^2 = 2 cur.d_i + |d_i|^2
        gain = 2 * (D.T @ cur) + np.diag(G)
        if chosen:
            gain[chosen] = np.inf
        i = int(np.argmin(gain))
        if not np.isfinite(gain[i]) or gain[i] >= 0:
            return chosen
        cur = cur + D[:, i]
        chosen.append(i)


def boundary_moves(problem, ctx, fit, refine_fn, target_size: int = 6, rounds: int = 4,
                   progress=None, floor=None):
    """Refine ctx.region (bool per element) at the element level around the fitted
    heterogeneity `fit` (fitting.Fit with params["heterogeneity"] = [log region, log rest]).
    refine_fn(region_params) -> Fit refits the scales by simulation for ctx.region as set.
    floor: the residual that noise and discretisation explain; once the fit is within it,
    further moves would only shape the region to them (rounds stop).
    Modifies ctx.region; returns the (possibly) improved fit."""
    from .fitting import Fit

    for rnd in range(rounds):
        if floor is not None and fit.rss <= floor:
            if progress:
                progress(f"region boundary: fit rss {fit.rss:.3e} within the floor {floor:.3e}, "
                         "boundary kept")
            break
        c = contrast(fit.params)
        if abs(c) < 1e-3:
            if progress:
                progress("region boundary: no stiffness contrast to locate")
            break
        region = ctx.region.copy()
        groups = boundary_groups(ctx.mesh, region, target_size, seed=rnd)
        if not groups:
            break
        # moving a group changes its elements' log stiffness by -contrast (region -> rest) or
        # +contrast (rest -> region)
        Dir = np.zeros((ctx.mesh.num_tets, len(groups)))
        for j, g in enumerate(groups):
            Dir[g, j] = np.where(region[g], -c, c)
        r_h, D = stiffness_jacobian(problem, ctx, fit.params, Dir)
        chosen = greedy_moves(r_h, D)
        if not chosen:
            if progress:
                progress(f"region boundary round {rnd + 1}: no move of {len(groups)} groups "
                         "is predicted to lower the residual")
            break
        accepted = False
        # the linear prediction of many combined moves can overshoot: the best half if not all
        for take in (chosen, chosen[: max(1, len(chosen) // 2)]):
            new = region.copy()
            for i in take:
                new[groups[i]] = ~new[groups[i]]
            if new.all() or not new.any():
                continue
            ctx.region = new
            cand = refine_fn(fit.params)
            if progress:
                progress(f"region boundary round {rnd + 1}: {len(take)} of {len(groups)} groups "
                         f"moved, rss {fit.rss:.3e} -> {cand.rss:.3e}")
            if cand.rss < fit.rss:
                small_gain = cand.rss > 0.99 * fit.rss
                fit = Fit(fit.name, cand.params, cand.rss, fit.dof,
                          fit.evaluations + cand.evaluations, fit.history)
                accepted = True
                break
            ctx.region = region
            if len(take) == 1:
                break
        if not accepted:
            ctx.region = region
            break
        if small_gain:  # converged: another round would not change the answer
            break
    return fit
