"""Locating and refining a stiffer or softer region with stiffness tangents (linearised.py)
instead of one simulation per patch or boundary group.

* `patch_map`: the per-patch log-stiffness map fitted by Gauss-Newton *on simulations* (tangents
  of all patches in one pass per iteration, every step checked by simulation), with a weak
  Tikhonov pull to the baseline: a patch the recordings barely load stays at the baseline
  instead of taking an arbitrary value. A linearisation at the baseline alone underestimates a
  large contrast and lets weakly loaded patches swing far (named heterogeneity bar: their
  ridge-scaled estimates reached |log E| 5-15 and made the region; IoU 0.19).
* `split_patches`: the two-level (region, rest) approximation of that map, patches ordered by
  their value, weighted by sqrt(precision x volume) (precision alone lets the strongly loaded
  clamp-side patches decide the threshold; volume alone trusts the barely loaded ones); the
  region is the level that departs from the baseline (the smaller part by volume was tried: on
  the named heterogeneity bar with 32 patches the soft half is the larger one, IoU 0.04).

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

from .linearised import patch_directions, scaled_context, stiffness_jacobian


def _debiased_jacobian(problem, r, J):
    """J of the raw residual -> J of the debiased one (fitting.debias): while the discrepancy's
    weight is inside its range the debiased residual is orthogonal to the discrepancy b (its
    direction is profiled out), and so is its derivative; at a clipped weight J is unchanged."""
    from .fitting import discrepancy

    b = discrepancy(problem, problem.train)  # (a stiffness patch does not move the damping)
    if b is None:
        return J
    bb = float(b @ b)
    if len(b) != len(r) or bb <= 0 or abs(float(r @ b)) > 1e-6 * np.sqrt(bb * float(r @ r) + 1e-300):
        return J
    return J - np.outer(b, b @ J) / bb


def patch_map(problem, ctx, labels, iterations: int = 5, pull: float = 0.02, max_step: float = 1.5,
              progress=None):
    """Per-patch log-stiffness map theta (#patches,) relative to ctx's model, fitted to the train
    residual by Levenberg-Marquardt Gauss-Newton with tangents (stiffness_jacobian, one pass for
    all patches per iteration), each step accepted only when the simulated residual drops.
    `pull`: Tikhonov weight towards 0 (the baseline) in units of the median patch precision
    (diag J^T J): a patch loaded far less than the median is left at the baseline.
    Returns (theta, rss, H = J^T J at theta)."""
    from .effects import build_model
    from .fitting import marker_residual

    D = patch_directions(labels)
    k = D.shape[1]
    th = np.zeros(k)
    r, J = stiffness_jacobian(problem, scaled_context(ctx, D @ th), {}, D)
    J = _debiased_jacobian(problem, r, J)
    cur, damp = float(r @ r), 1.0
    for it in range(iterations):
        H, g = J.T @ J, J.T @ r
        d = np.diag(H).copy()
        R = pull * float(np.median(d)) * np.eye(k)
        accepted = False
        while damp < 1e3:
            step = -np.linalg.solve(H + R + np.diag(0.05 * damp * d + 1e-12 * d.mean() + 1e-300),
                                    g + R @ th)
            if np.abs(step).max() > max_step:
                step *= max_step / np.abs(step).max()
            tn = np.clip(th + step, -4.0, 4.0)
            rn = marker_residual(problem, build_model(scaled_context(ctx, D @ tn), {}))
            if float(rn @ rn) < cur:
                accepted = True
                break
            damp *= 4.0
        if not accepted:
            break
        gain = cur - float(rn @ rn)
        th, damp = tn, max(damp / 3.0, 0.1)
        if progress:
            progress(f"patch map iteration {it + 1}: rss {cur:.3e} -> {float(rn @ rn):.3e}")
        cur = float(rn @ rn)
        if it + 1 < iterations:
            r, J = stiffness_jacobian(problem, scaled_context(ctx, D @ th), {}, D)
            J = _debiased_jacobian(problem, r, J)
        if gain < 0.01 * cur:
            break
    return th, cur, J.T @ J


def split_patches(theta, H, volumes):
    """Two-level approximation of a patch map: patches sorted by theta; every threshold gives a
    (region value, rest value) pair, the weighted means of its two sides with weights
    sqrt(precision x volume) (precision: diag H, both normalised to mean 1). The threshold is the
    one with the least weighted squared error to the map (choosing it by the simulated residual
    was tried: pipeline.diagnose). Returns (region mask over patches: the level farther from the
    baseline 0, (region value, rest value))."""
    theta = np.asarray(theta, float)
    d = np.diag(np.asarray(H, float))
    v = np.asarray(volumes, float)
    w = np.sqrt(d / max(d.mean(), 1e-300) * v / max(v.mean(), 1e-300)) + 1e-12
    o = np.argsort(theta)
    best = (np.inf, None, None)
    for j in range(1, len(o)):
        lo, hi = o[:j], o[j:]
        a = float(np.average(theta[lo], weights=w[lo]))
        b = float(np.average(theta[hi], weights=w[hi]))
        sel = np.zeros(len(theta), bool)
        sel[lo] = True
        err = float(w[lo] @ (theta[lo] - a) ** 2 + w[hi] @ (theta[hi] - b) ** 2)
        if err < best[0]:
            best = (err, sel, (a, b))
    if best[1] is None:
        return np.zeros(len(theta), bool), (0.0, 0.0)
    sel, (a, b) = best[1], best[2]
    if abs(b) > abs(a):
        sel, (a, b) = ~sel, (b, a)
    return sel, (a, b)


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
