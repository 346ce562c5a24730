"""The coarse model's discretisation bias in the diagnosis (`discretisation`): measured against
the once-refined mesh, removed from the train residual with a bounded weight (fitting.debias),
and the floor it leaves."""
from __future__ import annotations

import numpy as np

from . import fitting


# How far the truth lies beyond the once-refined mesh, as a multiple of the refined-minus-coarse
# discrepancy (linear tets, error ~ h^2): 0.55 for a truth meshed 1.5x finer than the model, 4/3
# for the continuum (Richardson).
DISC_RANGE = (0.55, 4.0 / 3.0)
# log stiffness offsets scanned when the offset's local fit never moves (coarse linear tets are too stiff)
# the discrepancy follows the candidate model's damping (_damping_columns; fitting.discrepancy):
# off by default (session 16: on the suites it gained one verdict and cost two, docs/results.md);
# `diagnose(..., follow_damping=True)` turns it on
DAMPING_FOLLOWS = False
# the plausible ratios of successive unit changes of b (geometric decay with the damping; 1: linear)
RATIO_RANGE = (0.2, 1.0)
OFFSET_GRID = (-0.05, -0.1, -0.2, -0.35, -0.5, -0.7, -0.9, -1.2)
# the local offset fit is checked against the first modes' stiffness ratio when they differ by more
MODAL_GAP = 0.1


def _refined_problem(P):
    """A Problem sharing P's recordings and start decisions on the once-refined scene, with no
    discrepancy of its own."""
    from .problem import Problem

    fine = Problem.__new__(Problem)
    fine.__dict__.update(P.__dict__)
    fine.scene = P.refined_scene()
    fine._emb = {}
    fine._nominal_omega = ()  # its own scene's lowest mode (P's start decisions are shared)
    fine._rest_offsets = {}
    fine.disc_bias = {}
    fine.simulations = 0
    return fine


def first_frequency(scene) -> float | None:
    """The lowest angular frequency (rad/s) of the scene's nominal material about its rest shape,
    clamped as the scene is (release.vibration_modes); None without a clamp (rigid modes) or when
    the eigensolver fails."""
    import scipy.sparse.linalg as spla

    from ..release import vibration_modes

    if len(scene.fixed) == 0:
        return None
    V = np.asarray(scene.mesh.vertices, float)
    free = np.setdiff1d(np.arange(len(V)), scene.fixed)
    try:
        lam = vibration_modes(scene.model(), V, (3 * free[:, None] + np.arange(3)).ravel(), 1)[0]
    except (RuntimeError, ValueError, spla.ArpackError):
        return None
    return float(np.sqrt(lam[0]))


def modal_offset(P, fine) -> float | None:
    """2 log(w_refined / w_coarse): the log stiffness factor with which the coarse mesh's lowest
    mode matches the once-refined mesh's (None where either has none)."""
    wc, wr = P.nominal_omega(), fine.nominal_omega()
    return None if wc is None or wr is None else float(2.0 * np.log(wr / wc))


def _usable(b: np.ndarray) -> bool:
    """A measured discrepancy, not a failed simulation's constant residual."""
    return bool(np.all(np.isfinite(b))) and float(np.abs(b).max(initial=0.0)) < 0.5


def _measure(P, fine, ctx, offset_params: dict, damping_params: dict) -> np.ndarray:
    """The refined-minus-coarse discrepancy of P's train recordings (raw residuals, nothing
    removed) with the damping of `damping_params` (effects.damping_of) on both meshes, the coarse
    model at the reference offset `offset_params` (b0 when the damping is the nominal one)."""
    from dataclasses import replace

    from .effects import damping_of

    damping = damping_of(ctx, damping_params)
    rf = fitting.marker_residual(fine, fine.scene.model(damping=damping), P.train)
    moved = replace(ctx, damping=damping)
    moved.clamp_layer = ctx.clamp_layer
    return rf - fitting.residual_pair(P, moved, offset_params, P.train)[1]


def _damping_columns(P, fine, ctx, offset_params: dict, b0: np.ndarray):
    """((N, 2) the change of the refined-minus-coarse discrepancy b over the first unit of alpha_M
    and of alpha_K (effects.DAMPING_STEPS), (2,) the ratio of its change over the second unit to
    that over the first): b re-measured with the damping moved by one and two units on both
    meshes (a unit is ~5 % of critical damping at the dominant frequency).
    The mesh error of a motion decays with its damping (a coarse mesh errs most in the
    high-frequency content that damping removes), so a fixed b0 credits the nominal damping with
    the data's: independent seed 12's L-bracket (alpha_M 0.18 -> 4.5 1/s, truth nested 1:8)
    leaves 0.113 with the truth's damping and b0 against 0.112 for the nominal model, and 0.077
    (the marker noise 0.071) with the discrepancy re-measured at the truth's damping. The change
    is geometric in the damping (fitting.discrepancy: each further unit changes b by `ratio`
    times the last), so a fit a few units away is not extrapolated linearly. The strain-dependent
    family's alpha_K polynomial is not followed (when it was, random seed 5's Rayleigh bar r5_09
    turned strain-dependent). None where a re-measured discrepancy is unusable."""
    from .effects import DAMPING_STEPS

    cols, ratios = [], []
    for step in DAMPING_STEPS:
        b1 = _measure(P, fine, ctx, offset_params, step)
        b2 = _measure(P, fine, ctx, offset_params, {k: [2.0 * x for x in v] for k, v in step.items()})
        if not (_usable(b1) and _usable(b2)):
            return None
        d1, d2 = b1 - b0, b2 - b1
        cols.append(d1)
        ratios.append(float(np.clip(float(d2 @ d1) / max(float(d1 @ d1), 1e-300), *RATIO_RANGE)))
    return np.stack(cols, axis=1), np.array(ratios)


def discretisation(P, ctx, say, follow_damping: bool | None = None):
    """The mesh's discretisation bias, its removal, and the floor it leaves.

    Coarse linear tets are too stiff. The nominal model is re-simulated on the once-refined mesh
    (every train recording) and the coarse model's stiffness offset theta_r that best matches it
    is fitted (first recording). How far the recordings' "truth" lies beyond the refined mesh is
    unknown: from a mesh 1.5x finer than the model's to the continuum (DISC_RANGE times the
    refined-minus-coarse discrepancy). Two bounded nuisances remove it:
    - the baseline every family is fitted on top of takes the data's best stiffness offset,
      clipped to DISC_RANGE * theta_r;
    - what the offset leaves of the refined-minus-coarse marker discrepancy, b, is added to every
      train prediction with a weight profiled out of each fit inside DISC_RANGE
      (fitting.debias: multi-fidelity additive correction), so the data's discretisation error
      is removed instead of only floored.
    The floor is what the weight's uncertainty (half its range) leaves of b; the conservative
    floor assumes a truth as far as the continuum whose error need not follow b's spatial
    pattern at all: (4/3)^2 |b|^2 (a truth meshed in another pattern, or a model only 1-2 tets
    across, leaves up to ~2 |b|^2 after the correction; a well-resolved one ~0.02 |b|^2). The
    marker noise is added by the caller.
    Returns (baseline context, (floor rss, conservative floor rss), offset theta, (b, scale),
    raw rss of the nominal model as given, nothing removed):
    b the stacked discrepancy over all train recordings and scale the factor that turns an rss
    of b into floor units (for ranking.discretisation_credit: what a family can gain by
    mimicking the discrepancy the correction leaves)."""
    from dataclasses import replace

    fine = _refined_problem(P)
    P.disc_bias = {}
    P.disc_bias_damping = {}
    P.disc_bias_ratio = None
    recs = P.train
    rc = fitting.marker_residual(P, P.scene.model(), recs)
    rf = fitting.marker_residual(fine, fine.scene.model(), recs)
    P.simulations += fine.simulations
    first = slice(0, 3 * int(recs[0].seen.sum()))  # the offset is measured on one recording
    fit = fitting.refine(P, ctx, ["stiffness_scale"], {}, r_start=(rc - rf)[first], iterations=2,
                         target=rf[first], recs=recs[:1])
    # Coarse tets are too stiff, so an offset of exactly zero means the local fit never moved
    # (every step rejected) and the offset's range would collapse to a point: then the best of a
    # grid of softer offsets is refined instead (independent suite, seed 12, a 288-tet plate with
    # a hole: the refined mesh matches 0.45x; the range had collapsed to [1, 1] and none of the
    # discrepancy was removed). Only then: tried in session 12 after every local fit, the grid's
    # better offsets shrank the discrepancy left after the offset (named stiffness bar 6.9e-2 ->
    # 1.0e-3) and with it the floor and every family's credit, while the truth's mesh error,
    # in another pattern, stays; three named cases turned to a family mimicking that error
    # (stiffness scale -> heterogeneity, support compliance -> Poisson ratio, stiffness +
    # damping -> tension nonlinearity)
    if fit.params["stiffness_scale"][0] == 0.0:
        best = fitting.scan(P, ctx, "stiffness_scale", OFFSET_GRID[0], (rc - rf)[first],
                            grid=OFFSET_GRID[1:], target=rf[first], recs=recs[:1])
        if best[0] != 0.0:
            fit = fitting.refine(P, ctx, ["stiffness_scale"], {"stiffness_scale": best}, iterations=2,
                                 target=rf[first], recs=recs[:1])
    # The local fit starts at 0 and an oscillation's phase makes its landscape multimodal: where
    # the coarse mesh is far too stiff it stops in another basin (independent suites: L-brackets,
    # plates and tori whose lowest modes ask 0.38-0.53 fitted 0.76-1.31, a refined mesh "stiffer"
    # than its coarse one, and the whole baseline off by that much). The lowest modes' ratio is a
    # second start; the better match is kept (the named suite's offsets agree with it within 0.1
    # but one, and are left as they were).
    theta_m = modal_offset(P, fine)
    P.disc_modal_factor = None if theta_m is None else float(np.exp(theta_m))
    if theta_m is not None and abs(theta_m - float(fit.params["stiffness_scale"][0])) > MODAL_GAP:
        alt = fitting.refine(P, ctx, ["stiffness_scale"], {"stiffness_scale": [theta_m]}, iterations=2,
                             target=rf[first], recs=recs[:1])
        say(f"discretisation: the local offset fit {np.exp(fit.params['stiffness_scale'][0]):.3f} (rss "
            f"{fit.rss:.3e}), from the lowest modes' ratio {np.exp(theta_m):.3f}: "
            f"{np.exp(alt.params['stiffness_scale'][0]):.3f} (rss {alt.rss:.3e})")
        if alt.rss < fit.rss:
            fit = alt
    theta_r = float(fit.params["stiffness_scale"][0])
    b = rf - fitting.residual_of(P, ctx, fit.params, recs)
    lo, hi = sorted((DISC_RANGE[0] * theta_r, DISC_RANGE[1] * theta_r))
    if _usable(b):
        sizes = np.cumsum([3 * int(r.seen.sum()) for r in recs])[:-1]
        before = fine.simulations
        follow = DAMPING_FOLLOWS if follow_damping is None else follow_damping
        got = _damping_columns(P, fine, ctx, fit.params, b) if follow else None
        P.simulations += fine.simulations - before
        P.disc_bias = {id(r): part for r, part in zip(recs, np.split(b, sizes))}
        P.disc_weight_range = DISC_RANGE
        if got is not None:
            P.disc_bias_damping = {id(r): part for r, part in zip(recs, np.split(got[0], sizes))}
            P.disc_bias_ratio = got[1]
    else:
        b = np.zeros_like(b)
    data = fitting.refine(P, ctx, ["stiffness_scale"], {"stiffness_scale": [theta_r]}, iterations=2)
    theta = float(np.clip(data.params["stiffness_scale"][0], lo, hi))
    scale = (0.5 * (DISC_RANGE[1] - DISC_RANGE[0])) ** 2
    rss_disc = scale * float(b @ b)
    rss_wide = DISC_RANGE[1] ** 2 * float(b @ b)
    mat = ctx.material
    E = np.asarray(mat.youngs_modulus, float) * np.exp(theta)
    new = replace(ctx, material=replace(mat, youngs_modulus=E), offset_applied=theta,
                  offset_reference=theta_r, offset_range=(lo, hi))
    new.clamp_layer = ctx.clamp_layer
    say(f"discretisation: coarse-vs-refined rss {float((rc - rf) @ (rc - rf)):.3e}, after "
        f"stiffness offset {float(b @ b):.3e} (removed with a weight in {DISC_RANGE}); offset "
        f"range [{np.exp(lo):.3f}, {np.exp(hi):.3f}], data {np.exp(data.params['stiffness_scale'][0]):.3f}")
    return new, (float(rss_disc), float(rss_wide)), theta, (b, scale), float(rc @ rc)
