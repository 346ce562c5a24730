"""`diagnose(scene, out_dir)`: where the gap lies, which effect explains it, how far it shrinks.

Steps (method.md section 9):
1. nominal residual on the train recordings with the mesh's discretisation discrepancy removed
   (the nominal model re-simulated on a once-refined mesh, its discrepancy subtracted with a
   bounded weight profiled out of every fit: fitting.debias); the error floor (marker noise from
   the tracks, what the correction leaves, and a conservative floor for significance);
2. where: control forces of a marker-following constrained simulation -> element shares,
   regions, frames, regimes;
3. which: sensitivities of every family (and of spatial patches, which locate a heterogeneity,
   refined at the element level), cheap linear fits, simulation refinement of the most promising
   families (with the discretisation offset as a bounded nuisance), evidence ranking (a fit
   leads only by more than it could gain by mimicking the measured discretisation error;
   ranking.py), nested pairs decided by that gain + leave-one-recording-out, confounding,
   forward selection of further effects, a joint refit of the verdict, history-dependence test
   (per-recording and late-time material against the best stateless addition; history.py);
4. how much: the held-out (test) gap before and after adding the verdict's effects one by one.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from . import contract, decay, fitting, history, ranking, region, simcache, where
from .discretisation import discretisation
from .effects import CANDIDATES, FAMILIES, NUISANCE, WITH_NUISANCE, EffectContext, build_model, describe
from .problem import Problem, marker_spectrum_peak
from .selection import (ADD_FACTOR, DISSIPATIVE, EXPLAINED_MIN, GAP_FACTOR, NESTS, SURPRISE,
                        _add_nested_ties, _dof, _explained_excess, _forward_select, _linearisation_refuted,
                        _pair_challenge, _pair_rescue, _rank, _resolve_nested, _shortfall_replacements,
                        _still_unexplained, _support_or_region)

# per-recording start decision (problem.start_in_motion); False: every recording starts at rest
START_DECISION = True


# Families no recording can tell apart, whatever their fits: every load a recording has is
# gravity (an acceleration) or a prescribed motion, so the dynamics depend on E / rho only and a
# density scale c acts exactly as a stiffness scale 1 / c (formats.md: such effects carry
# `confounded_with` each other in every ranking, claimed or not).
TWINS = {"stiffness_scale": "density", "density": "stiffness_scale"}


def _printer(progress):
    t0 = time.time()

    def say(msg):
        line = f"[diagnose {time.time() - t0:6.1f}s] {msg}"
        if progress is None:
            print(line, file=sys.stderr, flush=True)
        else:
            progress(line)

    return say


def dominant_omega(problem) -> float:
    """Angular frequency of the strongest marker oscillation in the train recordings (rad/s)."""
    best, span = (0.0, 0.0), 1.0
    for rec in problem.train:
        got = marker_spectrum_peak(rec)
        if got is None:
            continue
        span = max(span, got[2]) if best[0] == 0 else span
        if got[0] > best[0]:
            best, span = got[:2], got[2]
    return float(2 * np.pi * max(best[1], 1.0 / span))


def scene_with_markers(scene, out_dir, log=None):
    """The scene to diagnose: `scene` (a scene.toml path or a Scene) itself, or, when some of its
    recordings have point clouds and no markers (formats.md allows cloud-only recordings; the
    diagnosis compares markers), a copy written to out_dir/tracked/scene.toml whose cloud-only
    recordings are replaced by the mesh tracked through their clouds, as `matlearn learn` does
    (clouds.prepare.track_scene; cached there by fingerprint). `diagnose` calls it first, so the
    CLI and the Python API diagnose the same recordings."""
    from ..clouds.prepare import is_cloud_only, track_scene
    from ..recording import load_recording
    from ..scene import Scene, load_scene, save_scene

    loaded = scene if isinstance(scene, Scene) else load_scene(scene)
    if not any(is_cloud_only(load_recording(p)) for p, _ in loaded.recordings):
        return scene if isinstance(scene, Scene) else Path(scene)
    tracked, _ = track_scene(loaded, Path(out_dir) / "tracked", log=log, progress=log is not None)
    return save_scene(tracked, Path(out_dir) / "tracked" / "scene.toml")


def diagnose(scene_path, out_dir, seed: int = 0, progress=None, patches: int = 16,
             refine_top: int = 3, report: bool = True, residual_source: str = "constrained",
             follow_damping: bool | None = None, resume: bool = False) -> dict:
    """Diagnose the scene's nominal model (scene_path: a scene.toml or a Scene; cloud-only
    recordings are tracked first, scene_with_markers) against its train recordings; write
    out_dir/diagnosis.json (formats.md), report.html and residual .vtu files; return the dict.

    residual_source: where the "where" control forces come from: "constrained" (a simulation
    prescribing the marker-nearest vertices; cheap) or "spacetime" (the learning step's reduced
    space-time optimisation; full-space forces, ~5x the cost). patches: spatial patches whose
    stiffness sensitivities locate a heterogeneity; refine_top: families refined by simulation.
    follow_damping: the discretisation discrepancy removed follows each candidate's Rayleigh
    damping, with each fit's own floor (discretisation._damping_columns; default
    discretisation.DAMPING_FOLLOWS, off: an experiment of session 16, docs/results.md).
    resume: continue a killed diagnosis of the same scene into the same out_dir: every simulation
    it finished is taken from out_dir/.diagnose_cache (simcache.py; the folder holds the run's
    simulated markers while it runs and is removed once diagnosis.json is written; without
    resume an earlier run's folder is cleared first)."""
    say = _printer(progress)
    out = Path(out_dir)
    np.random.seed(seed)
    scene_path = scene_with_markers(scene_path, out, say)  # cloud-only recordings tracked first
    # a recording that does not say it starts at rest starts in motion only where its own data
    # show it (problem.start_in_motion), decided once here for every recording
    P = Problem(scene_path, estimate_velocity="auto" if START_DECISION else False)
    out.mkdir(parents=True, exist_ok=True)  # once the scene has loaded: a bad one leaves no folder
    P.store = simcache.SimulationStore(out / simcache.FOLDER, resume=resume)
    if resume:
        say(f"resuming: {P.store.resumed} simulation(s) of the interrupted run found in {P.store.folder}"
            if P.store.resumed else f"resume: no interrupted run in {out} (no {simcache.FOLDER}), starting afresh")
    scene = P.scene
    nominal = scene.model()
    say(f"scene: {scene.mesh.num_tets} tets, {len(P.train)} train / {len(P.test)} test recordings")
    for role, recs in (("train", P.train), ("test", P.test)) if P.estimate_velocity == "auto" else ():
        for i, rec in enumerate(recs):
            info = P.start_info(rec)
            if "rss_moving" in info:
                say(f"{role} recording {i}: starts {'in motion' if info['moving'] else 'at rest'} (best "
                    f"uniform-stiffness rss from rest {info['rss_rest']:.3e}, moving {info['rss_moving']:.3e}, "
                    f"noise {info['rss_noise']:.3e})")

    # ---- where
    got = [where.residual_field(P, nominal, rec, residual_source) for rec in P.train]
    fields = [g[0] for g in got]
    field = where.merge(fields)
    shares = where.element_shares(field)
    regions = where.find_regions(scene.mesh, shares, seed=seed)
    regime = where.regime_split(field)
    by_time = where.share_by_time(fields[0])
    strain = np.abs(field.Fh - 1.0)
    d_ref = float(max(np.percentile(strain, 95), 1e-3))
    ctx = EffectContext(scene.mesh, scene.material, scene.damping, scene.fixed, d_ref=d_ref,
                        omega=dominant_omega(P))
    say(f"where: {len(regions)} region(s); regime {regime}; d_ref {d_ref:.3g}, omega {ctx.omega:.3g}")

    # ---- discretisation-compensated baseline and the floor
    sigma = P.noise_sigma() / P.object_size
    base_ctx, (rss_disc, rss_disc_wide), theta_disc, (d_res, d_scale), rss_nominal_raw = \
        discretisation(P, ctx, say, follow_damping)
    ctx = base_ctx
    r0, r0_raw = fitting.residual_pair(P, ctx, {})
    rss0 = float(r0 @ r0)
    n_eff = float(sum(len(r.times) for r in P.train))
    rss_noise = sigma**2 * len(r0)
    # the noise rss is estimated: it is uncertain by its chi-square fluctuation (two deviations).
    # rss_floor: what is left once the discretisation discrepancy is removed (claims are made
    # above it); rss_wide: the conservative floor, as if the truth's discretisation error could
    # lie anywhere up to (4/3)^2 |b|^2 in another spatial pattern (a gap is "significant", an
    # effect claimed without the marginal checks, or "unexplained" said, only beyond it)
    rss_noise_hi = rss_noise * (1.0 + 2.0 * np.sqrt(2.0 / max(len(r0), 1)))
    rss_floor = rss_noise_hi + rss_disc
    rss_wide = rss_noise_hi + rss_disc_wide
    # The discretisation correction assumes a truth finer than the model. Recordings that the
    # nominal model on its own mesh already matches within the marker noise (e.g. made with the
    # model's own mesh) hold no gap to explain: removing a discretisation error they do not have
    # would only invent one (a stiffness-type effect), so nothing is claimed.
    nominal_fits = rss_nominal_raw <= rss_noise_hi
    if nominal_fits:
        say(f"the nominal model matches the recordings within the marker noise (raw rss "
            f"{rss_nominal_raw:.3e} <= {rss_noise_hi:.3e}): no gap to explain")
    say(f"train rss {rss0:.3e} (discretisation-corrected baseline), floor {rss_floor:.3e} "
        f"(noise {rss_noise:.3e}, discretisation {rss_disc:.3e}; conservative {rss_wide:.3e}), "
        f"stiffness offset {np.exp(theta_disc):.3f}")
    # the recordings' modal decay against the nominal damping law (decay.py): blind to the mesh
    decay_ev = decay.evidence(P)
    say(decay.summary(decay_ev))

    # ---- which: sensitivities and cheap fits
    # Density is not simulated: every load in a recording is gravity (an acceleration) or a
    # prescribed motion, so the dynamics depend on E / rho only and a density scale c acts
    # exactly like a stiffness scale 1 / c (including Rayleigh damping). It gets the mirrored
    # stiffness fit and is reported as confounded with it.
    # (J_raw: the same sensitivities of the residual before the discretisation discrepancy is
    # removed, which tell how much a family resembles the mesh's error: ranking credit)
    J, J_raw = fitting.sensitivities(P, ctx, r0, [n for n in CANDIDATES if n not in ("heterogeneity", "density")],
                                     progress=lambda m: None, raw0=r0_raw)
    labels = fitting.make_patches(scene.mesh, patches, seed)
    Jp = np.zeros((len(r0), labels.max() + 1))
    Jp_raw = np.zeros_like(Jp)
    models = []
    for p in range(labels.max() + 1):  # simulated in parallel first (Problem.prefetch)
        ctx.region = labels == p
        models.append(build_model(ctx, {"heterogeneity": [0.1, 0.0]}))
    P.prefetch(models)
    for p in range(labels.max() + 1):
        ctx.region = labels == p
        r_p, raw_p = fitting.residual_pair(P, ctx, {"heterogeneity": [0.1, 0.0]})
        Jp[:, p] = (r_p - r0) / 0.1
        Jp_raw[:, p] = (raw_p - r0_raw) / 0.1
    # the region: the two-level split of the per-patch stiffness map fitted on simulations
    # (region.patch_map; the linearisation at the baseline misplaces it, see region.py); the
    # location linearised at the baseline stays a rival (its two levels from the same linear
    # fit), used when its simulated residual is lower by more than noise explains. (Choosing the map's threshold by the
    # simulated residual too was tried: it grows the region into the mesh's error, named
    # heterogeneity bar IoU 0.45 vs 0.66.)
    def two_level_rss(mask, ab):
        ctx.region = np.isin(labels, np.flatnonzero(mask))
        r = fitting.residual_of(P, ctx, {"heterogeneity": list(ab)})
        return float(r @ r)

    patch_theta, rss_map, H_map = region.patch_map(P, ctx, labels, progress=say)
    volumes = np.bincount(labels, weights=np.asarray(scene.mesh.rest_volumes), minlength=len(patch_theta))
    sel, het_start = region.split_patches(patch_theta, H_map, volumes)
    sel_lin, _ = fitting.locate_region(Jp, r0)
    ab_lin, _ = fitting.linear_fit(np.stack([Jp[:, sel_lin].sum(axis=1), Jp[:, ~sel_lin].sum(axis=1)], axis=1), r0)
    rss_split, rss_lin = two_level_rss(sel, het_start), two_level_rss(sel_lin, ab_lin)
    say(f"region: patch map split rss {rss_split:.3e}, linearised location rss {rss_lin:.3e}")
    if rss_lin < rss_split - ranking.noise_tolerance(rss_noise, len(r0), 2):
        sel, het_start = sel_lin, tuple(float(x) for x in ab_lin)
    ctx.region = np.isin(labels, np.flatnonzero(sel))
    say(f"patch map (log E) {np.round(patch_theta, 2).tolist()}, region patches {np.flatnonzero(sel).tolist()}")
    J["heterogeneity"] = np.stack([Jp[:, sel].sum(axis=1), Jp[:, ~sel].sum(axis=1)], axis=1)
    J_raw["heterogeneity"] = np.stack([Jp_raw[:, sel].sum(axis=1), Jp_raw[:, ~sel].sum(axis=1)], axis=1)
    say(f"sensitivities done ({P.simulations} simulations); region {int(ctx.region.sum())} tets")
    cheap = {}
    nuis = (ctx.offset_range[0] - ctx.offset_applied, ctx.offset_range[1] - ctx.offset_applied)
    for name, Jn in J.items():
        if name in WITH_NUISANCE:  # jointly with the bounded discretisation offset
            th, rss = _linear_fit_nuisance(Jn, J["stiffness_scale"][:, 0], r0, nuis)
        else:
            th, rss = fitting.linear_fit(Jn, r0)
        cheap[name] = (th, rss)
    cheap["density"] = (-cheap["stiffness_scale"][0], cheap["stiffness_scale"][1])
    # what each family could gain by mimicking the mesh's discretisation error (ranking.py), from
    # the raw sensitivities: the debiased ones are blind to the discrepancy's direction
    # (a located region's credit is that of a region re-located on the discrepancy itself: the
    # worst case. Its own columns' credit was tried: the tiny uniformly stiffer test bar
    # (test_diagnosis.py) was then called a region.)
    # The damping families move the discrepancy removed with them (fitting.discrepancy): what
    # they do to a model free of the mesh's error is their raw columns plus the discrepancy's
    # change at the baseline's weight, and that is what can mimic the error left (their raw
    # columns alone mostly re-shape the coarse mesh's own error, which the correction follows)
    J_credit = _credit_columns(P, J_raw, r0_raw)
    credit = ranking.discretisation_credit(J_credit, d_res, slice(0, len(d_res)), d_scale,
                                           j_offset=J_raw["stiffness_scale"][:, 0],
                                           region=(Jp_raw, fitting.locate_region))
    credit["density"] = credit["stiffness_scale"]
    # A located region chooses where it acts from the data: it can sit wherever the truth's mesh
    # error is left after the correction, whose size only the conservative floor bounds (a
    # truth in another pattern, a model 1-2 tets across: up to ~2 |b|^2). Its credit (measured
    # with the region re-located on the discrepancy itself) is scaled like that floor; the
    # other families act everywhere or at a fixed place (the clamp).
    credit["heterogeneity"] *= (rss_disc_wide / rss_disc) if rss_disc > 0 else 1.0
    # no family can gain more by mimicry than all the mesh's error the data can hold
    credit = ranking.Credits(credit, cap=rss_disc_wide)
    tol = {n: ranking.noise_tolerance(rss_noise, len(r0), _dof(n)) for n in cheap}
    say("discretisation credit: " + ", ".join(f"{n} {c:.2e}" for n, c in credit.items())
        + f" (charges capped at {credit.cap:.2e})")
    order = sorted(cheap, key=lambda n: fitting.score(cheap[n][1], _dof(n), n_eff, rss_floor))
    say("cheap fits (predicted rss): " + ", ".join(f"{n} {cheap[n][1]:.3e}" for n in order))

    # ---- refinement by simulation
    fits = {}
    to_refine = [n for n in order if n != "density"][:refine_top]
    if "stiffness_scale" not in to_refine:  # the commonest error; its linearisation is poorest
        to_refine.append("stiffness_scale")
    for big, (small, _) in NESTS.items():  # a nested pair is compared on equal terms
        if (big in to_refine) != (small in to_refine):
            to_refine.append(small if big in to_refine else big)
    to_refine.sort(key=lambda n: n in NESTS)  # the nested (smaller) family first

    def simulate_fit(name):
        start = {name: cheap[name][0]}
        if name == "heterogeneity":  # the two levels of the patch map
            start = {name: list(het_start)}
        elif len(FAMILIES[name].parameters) == 1:
            # oscillation phases make 1-parameter scale fits multimodal: scan before refining
            start = {name: fitting.scan(P, ctx, name, cheap[name][0], r0)}
        names = [name] + ([NUISANCE] if name in WITH_NUISANCE else [])
        fits[name] = fitting.refine(P, ctx, names, start, iterations=2, progress=say, r_zero=r0)
        if name in NESTS and NESTS[name][0] in fits:
            # the larger family from the smaller one's optimum: it can only do better
            small, embed = NESTS[name]
            emb = dict(fits[small].params)
            emb[name] = embed(emb.pop(small))
            alt = fitting.refine(P, ctx, names, emb, iterations=2, progress=say)
            if alt.rss < fits[name].rss:
                fits[name] = alt
        if name == "heterogeneity":  # coarse patches -> element-level region boundary
            # element-level moves are free to follow whatever mesh error the correction leaves,
            # which only the conservative floor bounds: no moves once the fit is within it
            fits[name] = fitting.refine_region(P, ctx, fits[name], progress=say, floor=rss_wide)
    for name in to_refine:
        simulate_fit(name)
    # A shortlisted family whose simulation gains far less than its linear prediction (e.g. a
    # damping fit whose linearised move leaves the physical range and is clipped away) held a
    # place another family may deserve: the next ones in the linear order are simulated in its
    # stead (found on random seed 5's compression bar r5_08: Rayleigh predicted
    # 1.39e-2 from 2.21e-2, simulated 2.21e-2, while compression, predicted 1.48e-2, was never
    # simulated)
    for name in _shortfall_replacements(fits, cheap, rss0, tol, order, to_refine):
        say(f"{name} simulated in place of a shortlisted family its simulation refuted")
        simulate_fit(name)
    # The linear predictions chose which families to simulate. Where a simulated fit gains far
    # more than its family's prediction (a gap so large that the linearisation at the nominal
    # model is poor), they cannot rule the others out either: every family they credit with any
    # gain is simulated too (independent suite seed 12, a tube on a 3.5x softer pad: the
    # stiffness scale predicted 9.75 from 10.44 and reached 0.447, while the clamp layer,
    # predicted 8.08, was never simulated)
    surprised, rest = _linearisation_refuted(fits, cheap, rss0, tol, order)
    if rest:
        say(f"{', '.join(surprised)} gained more than {SURPRISE:g}x the linear prediction: "
            f"{', '.join(rest)} simulated too")
    for name in rest:
        simulate_fit(name)
    # Likewise when no simulated fit explains the data: while the best of them still leaves a
    # significant residual (beyond GAP_FACTOR x the conservative floor, the bar a gap must pass
    # to be called significant) the linear order has not found an explanation and cannot rule
    # the other families out (random seed 6's soft support r6_01: the stiffness scale predicted
    # 16.3 from 24.9 and reached 0.391, 2.8x its prediction, 43x the floor; the clamp layer,
    # predicted 18.3, was never simulated; simulated, it reaches 0.081)
    rest = [] if nominal_fits else _still_unexplained(fits, cheap, rss0, order, GAP_FACTOR * rss_wide)
    if rest:
        say(f"the simulated fits leave {min(f.rss for f in fits.values()):.3e} > {GAP_FACTOR:g}x the "
            f"conservative floor: {', '.join(rest)} simulated too")
    for name in rest:
        simulate_fit(name)
    if "stiffness_scale" in fits:
        f = fits["stiffness_scale"]
        fits["density"] = fitting.Fit("density", {"density": -f.params["stiffness_scale"]}, f.rss,
                                      f.dof, 0, f.history)
    ranked = _rank(fits, cheap, order, n_eff, rss_floor, rss0, credit, tol, rss_noise)

    # ---- verdict
    # above: beyond the floor left once the discretisation discrepancy is removed; significant:
    # beyond the conservative floor's own uncertainty (GAP_FACTOR). In between an effect is
    # claimed only when it explains most of the residual above the marker noise and its fit
    # carries over to recordings it was not fitted on; "unexplained" needs a significant gap.
    # The floor is that of the model it is measured for: the discrepancy follows the damping
    # (fitting.discrepancy), so a fit whose damping differs from the nominal one leaves a floor of
    # its own. The baseline is above the floor when it exceeds its own or that of a fit that
    # gains beyond the noise (a more damped truth has less high-frequency mesh error left: random
    # independent seed 11's L-bracket, alpha_M 0.18 -> 5.2 1/s, baseline 0.107 inside its floor
    # 0.117, Rayleigh fitted 0.037 against its own floor 0.05)
    own_floor = {n: _own_floor(P, ctx, f, rss_floor, rss_noise_hi, d_scale) for n, f in fits.items()}
    gate_floor = min([rss_floor] + [own_floor[n] for n, f in fits.items() if rss0 - f.rss > tol.get(n, 0.0)])
    above = rss0 > gate_floor and not nominal_fits
    significant = above and rss0 > GAP_FACTOR * rss_wide
    verdict, selected = [], None
    cv = {}

    def cv_of(name, fit, relocate=False, claim=False):
        """Leave-one-recording-out residual of a fitted family (cached). relocate: a located
        region is located again per fold (the location is tested too; a location needs both
        kinds of motion, so this is used only where a gap is marginal). claim: for the claim of
        a marginal gap (does the effect carry over at all?): a fold's refit moves only where its
        recordings prefer it beyond their noise (fitting.loo_rss noise_var), so an uninformative
        recording is inconclusive, not evidence against (the nested comparisons keep the plain
        refit, which weighs two families on equal terms)."""
        key = name + ("/relocated" if relocate and name == "heterogeneity" else "/claim" if claim else "")
        if key not in cv:
            if key == "heterogeneity/relocated":
                cv[key] = fitting.loo_rss_region(P, ctx, fit.params, Jp, r0, labels)
            else:
                cv[key] = fitting.loo_rss(P, ctx, fit.params, noise_var=sigma**2 if claim else None)[0]
        return cv[key]

    if above:
        side = _support_or_region(ranked, ctx, say)
        best, forced = _resolve_nested(ranked, cv_of, credit, tol, say, floor_wide=rss_wide,
                                       half=ranking.explanation_bar(rss0, rss_noise))
        for winner, loser in side.items():
            # a stiff clamp layer is the region's description: whatever the region's nested
            # comparison chose (the uniform scale, where the region is not established) leads it
            winner = best["name"] if loser == "support_compliance" else winner
            forced.setdefault(winner, loser)
            forced.setdefault("_ties", []).append((winner, loser))
        ranking.confounded(ranked, credit, tol, rss0, forced, rss_noise)
        _add_nested_ties(ranked, forced)
        ranked[:] = ranking.order(ranked, credit, tol, forced)
        if best is not ranked[0] and best["name"] in ranked[0]["confounded_with"] + [ranked[0]["name"]]:
            ranked.remove(best)
            ranked.insert(0, best)
        fit = best["_fit"]
        ok = fit is not None and _explained_excess(
            fit.rss, rss0, min(rss_floor, own_floor.get(best["name"], rss_floor))) >= EXPLAINED_MIN
        if ok and not significant:
            loo = cv_of(best["name"], fit, relocate=True, claim=True)
            carried = loo is None or rss0 - loo >= 0.5 * (rss0 - fit.rss)
            # most of what is not marker noise (no stateless effect can explain noise)
            share = (rss0 - fit.rss) / max(rss0 - rss_noise, 1e-300)
            ok = share >= EXPLAINED_MIN and carried
            say(f"marginal gap ({rss0 / rss_wide:.2f} x conservative floor): {best['name']} explains "
                f"{share:.2f} of the residual above the noise, leave-one-recording-out rss {loo}: "
                f"claimed {ok}")
        rescued = None
        if not ok and significant:
            # no single family explains the significant gap: two together may (_pair_rescue)
            rescued = _pair_rescue(P, ctx, ranked, n_eff, rss_floor, rss0, credit, tol, say)
        if ok or rescued:
            if rescued:
                verdict, selected = rescued
            else:
                verdict, selected = [best["name"]], fit
                verdict, selected = _pair_challenge(P, ctx, ranked, verdict, selected, n_eff, rss_floor,
                                                    credit, tol, say)
            selected = _forward_select(P, ctx, selected, ranked, verdict, n_eff, rss_wide, rss0, say)
            # final refit of the verdict's parameters together (what the held-out gap uses)
            polished = fitting.refine(P, ctx, list(selected.params), selected.params, iterations=4,
                                      progress=say)
            if polished.rss < selected.rss:
                selected = polished
        elif significant:
            verdict = ["unexplained"]
    if decay_ev["change"] and not any(v in DISSIPATIVE for v in verdict):
        verdict, selected, decay_ev = _decay_claim(P, ctx, decay_ev, verdict, selected, ranked, say)
    hist = history.check(P, ctx, selected, rss_floor, say, add_factor=ADD_FACTOR, stateless=J,
                         strains=history.damage_strains(fields)) if above else None
    if hist is not None and hist["detected"]:
        verdict = ["history_dependence"] + [v for v in verdict if v != "unexplained"]
    say(f"verdict {verdict}")

    # ---- how much: held-out gaps
    cumulative_params = _cumulative_params(verdict, selected.params if selected else {})
    wanted = {"before": (nominal, False), "offset": ({}, False)}  # {key: (model or effects, fast)}
    wanted.update({("with", n): (p, False) for n, p in cumulative_params.items()})
    for e in ranked:  # an effect not in the verdict: its own gap (its refined or its linearised fit)
        if e["name"] not in cumulative_params:
            fit = e["_fit"]
            wanted[("alone", e["name"])] = (fit.params if fit else {e["name"]: _theta_of(e, selected, cheap)}, True)
    if hist is not None and hist["parameters"]:
        wanted["history"] = (hist["reference"], False)
    gaps, refined_gap = _held_out_gaps(P, ctx, wanted)
    gap_before = gaps["before"]  # None: the nominal model fails there
    # the mesh's share of the gap: the nominal material with only the stiffness offset the
    # coarse mesh takes (no effect added), so a user sees how much a finer mesh would remove
    disc_report = {"stiffness_factor": float(np.exp(ctx.offset_applied)),
                   "refined_mesh_factor": float(np.exp(ctx.offset_reference)),
                   "refined_mesh_modal_factor": P.disc_modal_factor,
                   "factor_range": [float(np.exp(t)) for t in ctx.offset_range],
                   "gap_with_offset": gaps["offset"],
                   "gap_refined_mesh": refined_gap}
    if disc_report["gap_refined_mesh"] and gap_before:
        from .report import gap_label

        say(f"{gap_label(bool(P.test))} {gap_before['max_error_pct']:.2f} %; "
            f"the nominal material on the once-refined mesh {disc_report['gap_refined_mesh']['max_error_pct']:.2f} %")
    cumulative = {name: gaps[("with", name)] for name in cumulative_params}
    # the effects list is ranked best first (formats.md): the verdict's effects lead, in its order
    # (a pair chosen jointly, _pair_challenge, can rank below a single family it replaced)
    front = [r for v in verdict for r in ranked if r["name"] == v]
    ranked[:] = front + [r for r in ranked if all(r is not f for f in front)]
    effects = []
    for e in ranked:
        name = e["name"]
        fit = e["_fit"]
        entry = {"name": name, "explained": e["explained"], "score": e["score"],
                 "parameters": describe(name, _theta_of(e, selected, cheap), ctx), "simulated": fit is not None,
                 "discretisation_credit": float(credit.get(name, 0.0))}
        if name in cumulative:
            entry["gap_after"] = cumulative[name]
        else:  # not in the verdict: the effect alone (its refined or its linearised fit)
            entry["gap_after"] = gaps[("alone", name)]
        twin = TWINS.get(name)
        confounded = e["confounded_with"] + ([twin] if twin and twin not in e["confounded_with"] else [])
        if confounded:
            entry["confounded_with"] = confounded
        if "evidence" in e:  # explained measured on other evidence than the train markers
            entry["evidence"] = e["evidence"]
        loo = cv.get(name, cv.get(name + "/claim"))
        if loo is not None:
            entry["loo_rss"] = loo
        effects.append(entry)
    if hist is not None:
        # outside the library: nothing can be added; the gap after is what the stateless reference
        # of the test leaves (the verdict's stateless effects, or the nominal model, with the
        # uniform stiffness refit), i.e. the best a correction N(Fh, Fhdot) of this kind reaches
        stateless = [cumulative[n] for n in verdict if n in cumulative and cumulative[n]]
        after = gaps.get("history")
        effects.append({"name": "history_dependence", "explained": hist["explained"],
                        "score": hist["score"], "parameters": hist["parameters"],
                        "gap_after": after or (stateless[-1] if stateless else (gap_before and dict(gap_before))),
                        "outside_library": True})
    for name in fitting.mark_held_out_changes(effects, verdict, gap_before):
        say(f"adding {name} grows the held-out gap: the train recordings do not determine it there")
    lead = next((e for e in effects if verdict and e["name"] == verdict[0]), {})
    if "heterogeneity" in verdict or "heterogeneity" in lead.get("confounded_with", []):
        # the located region leads `where` when a heterogeneity is concluded, or is one of the
        # explanations the data cannot tell apart from the first verdict effect
        het = where.region_entry(scene.mesh, np.flatnonzero(ctx.region), shares)
        regions = [het] + [r for r in regions if not set(r["elements"]) <= set(het["elements"])]
        _cap_shares(regions)
    result = {
        "object_size": P.object_size,
        "gap_before": gap_before,
        "where": {"regions": regions, "frames": {"share_by_time": by_time}, "regime": regime},
        "effects": effects,
        "verdict": verdict,
        "floor": {"rss_train": rss0, "rss_floor": rss_wide, "rss_floor_debiased": rss_floor,
                  "rss_noise": rss_noise, "rss_nominal_raw": rss_nominal_raw, "rss_discretisation": rss_disc_wide,
                  "rss_discretisation_debiased": rss_disc, "noise_sigma_m": sigma * P.object_size,
                  "significant": bool(significant)},
        "held_out": bool(P.test),
        "discretisation": disc_report,
        "decay": decay.report(decay_ev),
        "simulations": P.simulations,
        "residual_source": got[0][1],
    }
    contract.write(result, out / "diagnosis.json")  # formats.md: gaps always objects, strict JSON
    if report:
        from . import report as rep

        rep.write_report(out, P, ctx, result, shares, field, fits, selected, patch_theta, labels)
    say(f"wrote {out / 'diagnosis.json'} ({P.simulations} simulations"
        + (f", {P.store.hits} of them from the interrupted run)" if resume and P.store.resumed else ")"))
    P.store.remove()
    return result


def _decay_claim(P, ctx, ev, verdict, selected, ranked, say):
    """The verdict and its fit once the modal decay shows a damping change (decay.py) that the
    verdict has no damping family for: Rayleigh damping with coefficients that reproduce the
    measured decays, first where nothing else was concluded, added after the verdict's effects
    otherwise. The decays fix the damping at the measured frequencies; how it splits between
    alpha_M and alpha_K (the nominal ones scaled, only alpha_M moved, only alpha_K, or both
    fitted to decays at several frequencies) is chosen by the train markers' residual. The
    families' own marker fits are not used: their residual is debiased with the mesh's
    discrepancy measured at the nominal damping, which hides the change (decay.py). One
    amplitude per recording cannot tell Rayleigh from strain-dependent damping: the two are
    reported confounded. Returns (verdict, fit, the evidence with the chosen coefficients)."""
    name = "rayleigh_damping"
    base = dict(selected.params) if selected is not None else {}
    tried = {}
    for split in ev["candidates"]:
        params = dict(base, **{name: decay.rayleigh_theta(ctx, ev["candidates"][split])})
        r = fitting.residual_of(P, ctx, params)
        tried[split] = (float(r @ r), params)
    split = min(tried, key=lambda k: tried[k][0])
    ev = decay.choose(ev, split)
    claimed = [v for v in verdict if v != "unexplained"]
    new = [name] + claimed if not claimed else claimed + [name]
    fit = fitting.Fit("+".join(new), tried[split][1], tried[split][0],
                      sum(_dof(n) for n in new if n in FAMILIES))
    for row in ranked:
        if row["name"] == name:
            # what it explains is the decay mismatch (decay.explained), not the train markers'
            # residual, in which the mesh's discrepancy removed at the nominal damping hides it
            row["explained"], row["evidence"] = decay.explained(ev, P.scene.time_step), "decay"
            if "strain_dependent_damping" not in row["confounded_with"]:
                row["confounded_with"].append("strain_dependent_damping")
        if row["name"] == "strain_dependent_damping" and name not in row["confounded_with"]:
            row["confounded_with"].append(name)
    say("decay: train rss of the coefficient splits " + ", ".join(
        f"{k} ({ev['candidates'][k][0]:.3g} 1/s, {ev['candidates'][k][1]:.3g} s) {v[0]:.3e}" for k, v in tried.items()))
    say(f"decay: damping {ev['change']} than the nominal law (x{ev['ratio']:.2f} at the measured "
        f"frequencies, {ev['z']:.1f} standard errors): {name} with alpha_M {ev['alpha_mass']:.4g} 1/s, "
        f"alpha_K {ev['alpha_stiffness']:.4g} s ({split}); verdict {verdict} -> {new}")
    return new, fit, ev


def _theta_of(e, selected, cheap):
    """The parameters reported for the ranked family `e`: the verdict's joint fit, its own
    simulated fit, or its linear (cheap) fit."""
    name, fit = e["name"], e["_fit"]
    if selected and name in selected.params:
        return selected.params[name]
    return fit.params[name] if fit else cheap[name][0]


def _held_out_gaps(P, ctx, wanted: dict):
    """The held-out gaps the result reports, simulated side by side: wanted {key: (a model, or
    the effects' parameters on ctx, fast solver?)} -> ({key: gap, None where the model cannot be
    built or simulated on the held-out motion (reported, not hidden: contract.conform)}, the
    refined mesh's gap). Every model's predictions and the refined mesh's gap (`_refined_gap`)
    run as one batch (Problem.prefetch), a model once however often it is reported (by
    fingerprint, so the simulation count does not depend on the threads); the gaps are then
    read from the memoised predictions, the same numbers as one by one."""
    models, unique, fasts, seen = {}, [], [], set()
    for key, (what, fast) in wanted.items():
        try:
            m = build_model(ctx, what) if isinstance(what, dict) else what
        except (RuntimeError, ValueError):
            m = None
        models[key] = m
        if m is not None and (ident := (P.fingerprint(m), fast)) not in seen:
            seen.add(ident)
            unique.append(m)
            fasts.append(fast)
    refined = P.prefetch(unique, P.test or P.train, fasts, extra=[lambda: _refined_gap(P)])[0]
    gaps = {}
    for key, (_, fast) in wanted.items():
        try:
            gaps[key] = None if models[key] is None else fitting.gap(P, models[key], fast=fast)
        except (RuntimeError, ValueError):  # a failed or non-finite simulation
            gaps[key] = None
    return gaps, refined


def _refined_gap(P):
    """Held-out gap of the nominal material on the once-refined mesh (each tet split into 8, the
    same clamp and starts): what a finer mesh alone does to the gap. The stiffness factor of
    `gap_with_offset` is only the part of the mesh's error that a uniform scale mimics; a coarse
    mesh also errs in its mode shapes (independent seed 14's 288-tet plate with a hole: 18.64 %
    before, 18.41 % with its factor, 3.59 % on the refined mesh). None where the refined model
    cannot be simulated on the held-out motion."""
    from .discretisation import _refined_problem

    fine = _refined_problem(P)
    try:
        g = fitting.gap(fine, fine.scene.model())
    except (RuntimeError, ValueError):  # a failed or non-finite simulation
        g = None
    P.count(fine.simulations)
    return g


def _cumulative_params(verdict, params) -> dict:
    """{family: the fitted parameters of the verdict's library families up to and including it
    (with the discretisation offset)}, in verdict order; "history_dependence" (outside the
    library, it may lead the verdict) is skipped, not counted as a family."""
    fams = [v for v in verdict if v in FAMILIES]
    return {name: {n: params[n] for n in fams[: i + 1] + [NUISANCE] if n in params}
            for i, name in enumerate(fams)}


def _linear_fit_nuisance(Jn, j_offset, r0, bounds):
    """Linear fit of a family together with the discretisation offset column, the offset kept
    inside its plausible range `bounds` (clipped, the family refit with the offset fixed).
    Returns (family theta, predicted rss)."""
    th, rss = fitting.linear_fit(np.column_stack([Jn, j_offset]), r0)
    t_off = float(np.clip(th[-1], *bounds))
    if t_off != th[-1]:
        r_fixed = r0 + j_offset * t_off
        th_f, rss = fitting.linear_fit(Jn, r_fixed)
        return th_f, rss
    return th[:-1], rss


def _credit_columns(P, J_raw, r0_raw):
    """{family: columns} for the discretisation credit: the raw sensitivities, with the damping
    families' alpha_M and alpha_K columns (the first two of each, effects.DAMPING_STEPS) plus the
    discrepancy's change per unit of them (fitting.discrepancy's slope at the nominal damping)
    times the baseline's debias weight."""
    if not P.disc_bias_damping:
        return J_raw
    b0 = fitting.discrepancy(P, P.train)
    B = np.concatenate([P.disc_bias_damping[id(rec)] for rec in P.train])
    B = B * fitting.geometric_slope(P.disc_bias_ratio)
    w0 = fitting.debias_weight(P, r0_raw, b0)
    out = dict(J_raw)
    for name in ("rayleigh_damping", "strain_dependent_damping"):
        if name in out:
            cols = np.array(out[name], float)
            cols[:, :2] += w0 * B
            out[name] = cols
    return out


def _own_floor(P, ctx, fit, rss_floor, rss_noise_hi, d_scale):
    """The floor of a fitted model: the noise bound plus what the weight's uncertainty leaves of
    the discrepancy at the fit's damping (discretisation.discretisation's floor, re-measured);
    `rss_floor` itself where the discrepancy does not follow the damping."""
    from .effects import damping_coordinates

    d = damping_coordinates(ctx, fit.params)
    if not P.disc_bias_damping or not np.any(d):
        return rss_floor
    b = fitting.discrepancy(P, P.train, d)
    return float(rss_noise_hi + d_scale * float(b @ b))


def _cap_shares(regions):
    tot = sum(r["share"] for r in regions)
    if tot > 1:
        for r in regions:
            r["share"] /= tot
