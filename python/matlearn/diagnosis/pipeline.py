"""`diagnose(scene, out_dir)`: where the gap lies, which effect explains it, how far it shrinks.

Steps (method.md section 9):
1. nominal residual on the train recordings; the error floor (marker noise from the tracks, and
   discretisation from re-simulating the nominal model on a once-refined mesh);
2. where: control forces of a marker-following constrained simulation -> element shares,
   regions, frames, regimes;
3. which: sensitivities of every family (and of spatial patches, which locate a heterogeneity),
   cheap linear fits, simulation refinement of the most promising families, BIC ranking,
   confounding, forward selection of further effects, history-dependence test;
4. how much: the held-out (test) gap before and after adding the verdict's effects one by one.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from . import fitting, history, where
from .effects import CANDIDATES, FAMILIES, EffectContext, describe
from .problem import Problem

# Significance of the gap and of an explanation, in units of the floor (not tuned per case:
# a gap counts when its sum of squares exceeds the floor's by this factor, ~1.6x in RMS).
GAP_FACTOR = 2.5
EXPLAINED_MIN = 0.5  # an effect must explain this fraction of the residual above the floor
ADD_FACTOR = 0.6  # a further effect must cut (rss + floor) to this fraction
FLOOR_TIE = 1.5  # fits that both bring the residual down to ~the floor cannot be told apart
PRIOR = ("stiffness_scale", "rayleigh_damping", "poisson_ratio", "tension_nonlinearity",
         "compression_nonlinearity", "strain_dependent_damping", "support_compliance",
         "heterogeneity", "density")  # tie-break order: the commoner modelling error first


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
        m = np.nan_to_num(rec.markers - np.nanmean(rec.markers, axis=0))
        if len(m) < 8:
            continue
        t = rec.times
        span = max(span, t[-1] - t[0]) if best[0] == 0 else span
        tu = np.linspace(t[0], t[-1], len(t))
        sig = np.stack([np.interp(tu, t, m[:, k, d]) for k in range(m.shape[1]) for d in range(3)])
        P = (np.abs(np.fft.rfft(sig * np.hanning(len(tu)), axis=1)) ** 2).sum(0)
        f = np.fft.rfftfreq(len(tu), tu[1] - tu[0])
        P[0] = 0
        i = int(np.argmax(P))
        if P[i] > best[0]:
            best, span = (P[i], f[i]), t[-1] - t[0]
    return float(2 * np.pi * max(best[1], 1.0 / span))


def diagnose(scene_path, out_dir, seed: int = 0, progress=None, patches: int = 8,
             refine_top: int = 3, report: bool = True, residual_source: str = "constrained") -> dict:
    """Diagnose the scene's nominal model against its train recordings; write
    out_dir/diagnosis.json (formats.md), report.html and residual .vtu files; return the dict.

    residual_source: where the "where" control forces come from: "constrained" (a simulation
    prescribing the marker-nearest vertices; cheap) or "spacetime" (the learning step's reduced
    space-time optimisation; full-space forces, ~5x the cost). patches: spatial patches whose
    stiffness sensitivities locate a heterogeneity; refine_top: families refined by simulation."""
    say = _printer(progress)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    np.random.seed(seed)
    P = Problem(scene_path)
    scene = P.scene
    nominal = scene.model()
    say(f"scene: {scene.mesh.num_tets} tets, {len(P.train)} train / {len(P.test)} test recordings")

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
    base_ctx, rss_disc, theta_disc = _discretisation(P, ctx, say)
    ctx = base_ctx
    r0 = fitting.residual_of(P, ctx, {})
    rss0 = float(r0 @ r0)
    n_eff = float(sum(len(r.times) for r in P.train))
    rss_noise = sigma**2 * len(r0)
    rss_floor = rss_noise + rss_disc
    say(f"train rss {rss0:.3e} (compensated baseline), floor {rss_floor:.3e} "
        f"(noise {rss_noise:.3e}, discretisation {rss_disc:.3e}, stiffness offset {np.exp(theta_disc):.3f})")

    # ---- which: sensitivities and cheap fits
    # Density is not simulated: every load in a recording is gravity (an acceleration) or a
    # prescribed motion, so the dynamics depend on E / rho only and a density scale c acts
    # exactly like a stiffness scale 1 / c (including Rayleigh damping). It gets the mirrored
    # stiffness fit and is reported as confounded with it.
    J = fitting.sensitivities(P, ctx, r0, [n for n in CANDIDATES if n not in ("heterogeneity", "density")],
                              progress=lambda m: None)
    labels = fitting.make_patches(scene.mesh, patches, seed)
    Jp = np.zeros((len(r0), labels.max() + 1))
    for p in range(labels.max() + 1):
        ctx.region = labels == p
        Jp[:, p] = (fitting.residual_of(P, ctx, {"heterogeneity": [0.1, 0.0]}) - r0) / 0.1
    sel, patch_theta = fitting.locate_region(Jp, r0)
    ctx.region = np.isin(labels, np.flatnonzero(sel))
    J["heterogeneity"] = np.stack([Jp[:, sel].sum(axis=1), Jp[:, ~sel].sum(axis=1)], axis=1)
    say(f"sensitivities done ({P.simulations} simulations); region {int(ctx.region.sum())} tets")
    cheap = {}
    for name, Jn in J.items():
        th, rss = fitting.linear_fit(Jn, r0)
        cheap[name] = (th, rss)
    cheap["density"] = (-cheap["stiffness_scale"][0], cheap["stiffness_scale"][1])
    order = sorted(cheap, key=lambda n: fitting.score(cheap[n][1], _dof(n), n_eff, rss_floor))
    say("cheap fits (predicted rss): " + ", ".join(f"{n} {cheap[n][1]:.3e}" for n in order))

    # ---- refinement by simulation
    fits = {}
    to_refine = [n for n in order if n != "density"][:refine_top]
    if "stiffness_scale" not in to_refine:  # the commonest error; its linearisation is poorest
        to_refine.append("stiffness_scale")
    for name in to_refine:
        start = {name: cheap[name][0]}
        if len(FAMILIES[name].parameters) == 1:
            # oscillation phases make 1-parameter scale fits multimodal: scan before refining
            start = {name: fitting.scan(P, ctx, name, cheap[name][0], r0)}
        fits[name] = fitting.refine(P, ctx, [name], start, iterations=2, progress=say, r_zero=r0)
    if "stiffness_scale" in fits:
        f = fits["stiffness_scale"]
        fits["density"] = fitting.Fit("density", {"density": -f.params["stiffness_scale"]}, f.rss,
                                      f.dof, 0, f.history)
    ranked = _rank(fits, cheap, order, n_eff, rss_floor, rss0)

    # ---- verdict
    significant = rss0 > GAP_FACTOR * rss_floor
    verdict, selected = [], None
    best = ranked[0]
    if significant:
        if best["_fit"] is not None and _explained_excess(best["_fit"].rss, rss0, rss_floor) >= EXPLAINED_MIN:
            verdict, selected = [best["name"]], best["_fit"]
            selected = _forward_select(P, ctx, selected, ranked, verdict, n_eff, rss_floor, rss0, say)
        else:
            verdict = ["unexplained"]
    hist = history.check(P, ctx, selected, rss_floor, say) if significant else None
    if hist is not None and hist["detected"]:
        verdict = ["history_dependence"] + [v for v in verdict if v != "unexplained"]
    say(f"verdict {verdict}")

    # ---- how much: held-out gaps
    gap_before = P.gap(nominal)
    cumulative = {}
    for i, name in enumerate(v for v in verdict if v in FAMILIES):
        params = {n: selected.params[n] for n in verdict[: i + 1] if n in FAMILIES} if selected else {}
        cumulative[name] = _safe_gap(P, ctx, params)
    effects = []
    for e in ranked:
        name = e["name"]
        fit = e["_fit"]
        theta = selected.params[name] if (selected and name in selected.params) else (
            fit.params[name] if fit else cheap[name][0])
        entry = {"name": name, "explained": e["explained"], "score": e["score"],
                 "parameters": describe(name, theta, ctx), "simulated": fit is not None}
        if name in cumulative:
            entry["gap_after"] = cumulative[name]
        else:  # not in the verdict: the effect alone (its refined or its linearised fit)
            entry["gap_after"] = _safe_gap(P, ctx, fit.params if fit else {name: theta}, fast=True)
        if e["confounded_with"]:
            entry["confounded_with"] = e["confounded_with"]
        effects.append(entry)
    if hist is not None:
        # outside the library: nothing can be added, the gap stays what the stateless effects leave
        stateless = [cumulative[n] for n in verdict if n in cumulative and cumulative[n]]
        effects.append({"name": "history_dependence", "explained": hist["explained"],
                        "score": hist["score"], "parameters": hist["parameters"],
                        "gap_after": stateless[-1] if stateless else dict(gap_before),
                        "outside_library": True})
    if "heterogeneity" in verdict:
        het = where.region_entry(scene.mesh, np.flatnonzero(ctx.region), shares)
        regions = [het] + [r for r in regions if not set(r["elements"]) <= set(het["elements"])]
        _cap_shares(regions)
    result = {
        "object_size": P.object_size,
        "gap_before": gap_before,
        "where": {"regions": regions, "frames": {"share_by_time": by_time}, "regime": regime},
        "effects": effects,
        "verdict": verdict,
        "floor": {"rss_train": rss0, "rss_floor": rss_floor, "rss_noise": rss_noise,
                  "rss_discretisation": rss_disc, "noise_sigma_m": sigma * P.object_size,
                  "significant": bool(significant)},
        "held_out": bool(P.test),
        "simulations": P.simulations,
        "residual_source": got[0][1],
    }
    with open(out / "diagnosis.json", "w") as f:
        json.dump(result, f, indent=1)
    if report:
        from . import report as rep

        rep.write_report(out, P, ctx, result, shares, field, fits, selected, patch_theta, labels)
    say(f"wrote {out / 'diagnosis.json'} ({P.simulations} simulations)")
    return result


def _safe_gap(P, ctx, params, fast=False):
    """Held-out gap with the effects `params` added; None when the fitted model cannot be
    simulated on the held-out motion (reported, not hidden)."""
    try:
        return P.gap(fitting.build_model(ctx, params), fast=fast)
    except RuntimeError:
        return None


def _dof(name):
    return len(FAMILIES[name].parameters) + FAMILIES[name].extra_dof


def _explained_excess(rss, rss0, floor):
    return float((rss0 - rss) / max(rss0 - floor, 1e-300))


def _rank(fits, cheap, order, n_eff, floor, rss0):
    rows = []
    for name in order:
        fit = fits.get(name)
        rss = fit.rss if fit else cheap[name][1]
        rows.append({"name": name, "_fit": fit, "rss": rss,
                     "score": fitting.score(rss, _dof(name), n_eff, floor),
                     "explained": float(np.clip((rss0 - rss) / max(rss0, 1e-300), 0, 1))})
    for r in rows:
        r["confounded_with"] = []
    # two simulated fits explain the data equally when their residuals differ by less than half
    # the floor, or when both reach the floor (what is left is noise and discretisation)
    sim = [r for r in rows if r["_fit"] is not None]
    for a in sim:
        for b in sim:
            if a is b:
                continue
            ea, eb = rss0 - a["rss"], rss0 - b["rss"]
            big = max(ea, eb)
            both_at_floor = max(a["rss"], b["rss"]) <= FLOOR_TIE * floor
            if (big > 0 and min(ea, eb) > 0 and a["rss"] < 0.5 * rss0
                    and (abs(ea - eb) <= 0.5 * floor or both_at_floor)):
                a["confounded_with"].append(b["name"])
    # rank: simulated fits first, by score; within a confounded group by the prior order (the
    # commoner, simpler modelling error first), so a tie is flagged instead of decided by noise
    eff = {r["name"]: min([r["score"]] + [x["score"] for x in rows if x["name"] in r["confounded_with"]])
           for r in rows}
    rows.sort(key=lambda r: (r["_fit"] is None, round(eff[r["name"]], 6), PRIOR.index(r["name"])))
    return rows


def _forward_select(P, ctx, selected, ranked, verdict, n_eff, floor, rss0, say, max_effects=3):
    """Add further families while the joint refit cuts (rss + floor) by ADD_FACTOR."""
    for _ in range(max_effects - 1):
        if selected.rss < GAP_FACTOR * floor:
            break
        cands = [r for r in ranked if r["name"] not in verdict and r["_fit"] is not None
                 and r["name"] not in sum((x["confounded_with"] for x in ranked if x["name"] in verdict), [])]
        best = None
        for r in cands[:2]:
            names = list(selected.params) + [r["name"]]
            start = dict(selected.params)
            start[r["name"]] = r["_fit"].params[r["name"]]
            fit = fitting.refine(P, ctx, names, start, iterations=2, progress=say)
            if best is None or fit.rss < best.rss:
                best = fit
        if best is None or best.rss + floor > ADD_FACTOR * (selected.rss + floor):
            break
        added = [n for n in best.params if n not in verdict][0]
        verdict.append(added)
        selected = best
    return selected


def _cap_shares(regions):
    tot = sum(r["share"] for r in regions)
    if tot > 1:
        for r in regions:
            r["share"] /= tot


def _discretisation(P, ctx, say):
    """The mesh's discretisation bias and floor.

    Coarse linear tets are too stiff. The nominal model is re-simulated on the once-refined
    mesh and the coarse model's stiffness offset theta_r that best matches it is fitted. How
    far the recordings' "truth" lies beyond the refined mesh is unknown: from a mesh 1.5x finer
    than the model's (offset ~0.55 theta_r with error ~ h^2) to the continuum (4/3 theta_r). A
    stiffness offset in that interval is therefore not evidence of any effect: the baseline every
    family is fitted on top of takes the data's best offset clipped to it. The floor is what the
    offset cannot absorb, scaled by (4/3)^2, plus the marker noise (added by the caller).
    Returns (baseline context, floor rss, offset theta)."""
    from dataclasses import replace

    from .problem import Problem as _Problem

    fine = _Problem.__new__(_Problem)
    fine.__dict__.update(P.__dict__)
    fine.scene = P.refined_scene()
    fine._emb = {}
    fine.simulations = 0
    # the refined mesh costs ~10x: one train recording measures the offset
    recs = P.train[:1]
    rc = P.residual(P.scene.model(), recs)
    rf = fine.residual(fine.scene.model(), recs)
    P.simulations += fine.simulations
    fit = fitting.refine(P, ctx, ["stiffness_scale"], {}, r_start=rc - rf, iterations=2,
                         target=rf, recs=recs)
    # the floor counts all train recordings: scale by their share of the samples
    n_all = sum(int(r.seen.sum()) for r in P.train)
    share = n_all / max(sum(int(r.seen.sum()) for r in recs), 1)
    theta_r = float(fit.params["stiffness_scale"][0])
    lo, hi = sorted((0.55 * theta_r, 4.0 / 3.0 * theta_r))
    data = fitting.refine(P, ctx, ["stiffness_scale"], {"stiffness_scale": [theta_r]}, iterations=2)
    theta = float(np.clip(data.params["stiffness_scale"][0], lo, hi))
    rss_disc = (4.0 / 3.0) ** 2 * fit.rss * share
    mat = ctx.material
    E = np.asarray(mat.youngs_modulus, float) * np.exp(theta)
    new = replace(ctx, material=replace(mat, youngs_modulus=E), offset_applied=theta,
                  offset_reference=theta_r, offset_range=(lo, hi))
    new.clamp_layer = ctx.clamp_layer
    say(f"discretisation: coarse-vs-refined rss {float((rc - rf) @ (rc - rf)):.3e}, after "
        f"stiffness offset {fit.rss:.3e}; offset range [{np.exp(lo):.3f}, {np.exp(hi):.3f}], "
        f"data {np.exp(data.params['stiffness_scale'][0]):.3f}")
    return new, float(rss_disc), theta
