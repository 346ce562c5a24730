"""The decision rules of the diagnosis (pipeline.diagnose): which families are simulated beyond
the linear shortlist, the evidence order of the simulated fits, nested families and the support /
region pair, forward selection of further effects. Each takes the fits and floors diagnose
computed; they simulate only through `_forward_select`'s refits and the leave-one-recording-out
callback `_resolve_nested` is given."""
from __future__ import annotations

import numpy as np

from . import fitting, ranking
from .effects import FAMILIES, NUISANCE

# Significance of the gap and of an explanation, in units of the floor. The floor assumes the
# truth is the continuum (an upper bound of the discretisation error), but its shape is that of
# a once-refined mesh, so it is uncertain by about this factor (~1.6x in RMS): above it a gap is
# clear (an effect or "unexplained"); between 1x and this factor an effect must also explain
# most of the whole residual and carry over between recordings.
GAP_FACTOR = 2.5
EXPLAINED_MIN = 0.5  # an effect must explain this fraction of the residual above the floor
ADD_FACTOR = 0.6  # a further effect must cut (rss + floor) to this fraction
# a simulated fit gaining more than this multiple of its linearised prediction marks the
# linearisation as poor: every family with a predicted gain is then simulated
SURPRISE = 3.0
# a shortlisted family whose simulated gain is below this fraction of its linearised prediction
# is refuted: the next family in the linear order is simulated in its stead
SHORTFALL = 0.25
# nested families: larger -> (smaller, embedding of the smaller's parameters in the larger's)
NESTS = {
    "strain_dependent_damping": ("rayleigh_damping", lambda t: [t[0], t[1], 0.0, 0.0]),
    "heterogeneity": ("stiffness_scale", lambda t: [t[0], t[0]]),
}


def _dof(name):
    return len(FAMILIES[name].parameters) + FAMILIES[name].extra_dof


def _linearisation_refuted(fits, cheap, rss0, tol, order):
    """(families whose simulated fit gained more than SURPRISE x their linearised prediction
    plus the noise tolerance, the families still to simulate because of them: every family
    not simulated yet that the linear fits credit with any gain, nested (smaller) ones first)."""
    surprised = [n for n in fits if rss0 - fits[n].rss > SURPRISE * max(rss0 - cheap[n][1], 0.0) + tol[n]]
    if not surprised:
        return [], []
    rest = [n for n in order if n not in fits and n != "density" and cheap[n][1] < rss0]
    return surprised, sorted(rest, key=lambda n: n in NESTS)


def _still_unexplained(fits, cheap, rss0, order, bound):
    """The families still to simulate because every simulated fit leaves more than `bound`:
    every family not simulated yet that the linear fits credit with any gain, nested (smaller)
    ones first; none once a simulated fit is within the bound."""
    if not fits or min(f.rss for f in fits.values()) <= bound:
        return []
    rest = [n for n in order if n not in fits and n != "density" and cheap[n][1] < rss0]
    return sorted(rest, key=lambda n: n in NESTS)


def _shortfall_replacements(fits, cheap, rss0, tol, order, shortlist):
    """Families to simulate in place of shortlisted ones whose simulated gain fell below
    SHORTFALL x their linearised prediction (beyond noise): for each such family the next one in
    the linear order not simulated yet whose predicted gain exceeds the noise, with the smaller
    family of a nested pair it brings in first."""
    def predicted(n):
        return rss0 - cheap[n][1]
    refuted = [n for n in shortlist if n in fits and predicted(n) > tol[n]
               and rss0 - fits[n].rss < SHORTFALL * predicted(n)]
    queue = [n for n in order if n not in fits and n != "density" and predicted(n) > tol[n]]
    out = []
    for _ in refuted:
        if not queue:
            break
        nxt = queue.pop(0)
        small = NESTS.get(nxt, (None,))[0]
        if small is not None and small not in fits and small not in out:
            out.append(small)
            if small in queue:
                queue.remove(small)
        out.append(nxt)
    return out


def _explained_excess(rss, rss0, floor):
    return float((rss0 - rss) / max(rss0 - floor, 1e-300))


def _rank(fits, cheap, order, n_eff, floor, rss0, credit, tol, rss_noise=0.0):
    """Rows {name, _fit, rss, score, explained, confounded_with} in evidence order (ranking.py):
    a fit leads another only when its residual is lower by more than its discretisation credit
    and the noise; fits that cannot be told apart are confounded, and the prior order leads
    among them."""
    rows = []
    for name in order:
        fit = fits.get(name)
        rss = fit.rss if fit else cheap[name][1]
        rows.append({"name": name, "_fit": fit, "rss": rss,
                     "score": fitting.score(rss, _dof(name), n_eff, floor),
                     # the criterion's parameters, for ranking.credited: among fits the data
                     # cannot tell apart, the best one charged its credit leads
                     "_criterion": (_dof(name), n_eff, floor),
                     "explained": float(np.clip((rss0 - rss) / max(rss0, 1e-300), 0, 1))})
    ranking.confounded(rows, credit, tol, rss0, rss_noise=rss_noise)
    return ranking.order(rows, credit, tol)


def _add_nested_ties(rows, forced):
    """A nested pair the data cannot decide (ties recorded by _resolve_nested) is confounded."""
    ties = forced.get("_ties", [])
    for a, b in ties:
        for r in rows:
            if r["name"] == a and b not in r["confounded_with"]:
                r["confounded_with"].append(b)
            if r["name"] == b and a not in r["confounded_with"]:
                r["confounded_with"].append(a)


# A family fitted together with the discretisation offset (effects.WITH_NUISANCE) whose change
# acts on the stiffness everywhere contains a uniform stiffness scale inside the offset's range:
# the Poisson ratio with its offset is nested over the stiffness scale (a uniform scale is
# E / rho, so a density change is exactly such a scale, and a ratio fitted with its offset can
# absorb part of it: named density sphere, Poisson 6.12e-3 vs the scale's 6.26e-3, noise 5.5e-3).
# Only a Poisson ratio that already leads the ranking (it beat the scale by CREDIT_FACTOR x its
# credit) is re-examined: the comparison can take the lead from it, never give it one (its credit,
# measured on the once-refined mesh, underestimates volumetric locking, which converges slower
# than h^2: the tiny control bar 2 tets across needs a ratio 0.23 lower against 0.04 for the
# refined mesh's pattern, so at face value it would win there).
OFFSET_NESTS = {"poisson_ratio": "stiffness_scale"}
# larger families whose extra parameters are only an amplitude dependence (alpha_K growing with the
# strain over Rayleigh damping): unless the evidence prefers the larger one, the data are as
# consistent with it as with the smaller one (recordings of one amplitude each cannot show the
# dependence; decay.py), so the smaller one is reported confounded with it, as the decay claim
# reports it (pipeline._decay_claim). Independent seed 14's strain-dependent plate: Rayleigh
# explained 0.281, strain-dependent damping 0.284, verdict Rayleigh with nothing confounded.
AMPLITUDE_NESTS = ("strain_dependent_damping",)


def _resolve_nested(ranked, cv_of, credit, tol, say, floor_wide=None, half=None):
    """The best-ranked family, with a nested pair decided on evidence: the larger family (e.g.
    strain-dependent damping, which contains Rayleigh damping) is preferred only when both its
    criterion charged with its discretisation credit is lower (ranking.credited at face
    value) and its
    leave-one-recording-out residual is lower by more than the noise fluctuation (with one
    train recording, the criterion alone). When exactly one of the two prefers it, the data
    cannot tell them apart: the smaller one is reported, confounded with the larger (also when
    neither does and the larger adds only an amplitude dependence, `_amplitude_tie`). When the
    best is a smaller family that several larger ones contain (the stiffness scale: a located
    region, a Poisson ratio with its own scale), each pair is decided alone and, of the larger
    ones preferred, the best once charged its credit at face value leads. Returns (best row,
    forced decisions for ranking.order: {winner: loser or [losers], "_ties": [(a, b)]})."""
    best = ranked[0]
    rows = {r["name"]: r for r in ranked}
    forced = {}
    pairs = [(rows[big], rows[small]) for big, (small, _) in NESTS.items()
             if best["name"] in (big, small) and rows.get(big, {}).get("_fit")
             and rows.get(small, {}).get("_fit")]
    small = OFFSET_NESTS.get(best["name"])
    if small and rows.get(small, {}).get("_fit"):  # only a leading Poisson ratio is re-examined
        pairs.append((best, rows[small]))
    winners = []
    for big, small in pairs:
        by_score, by_cv = _nested_evidence(big, small, cv_of, credit, tol, say, floor_wide)
        if by_score and by_cv:
            winners.append((big, small))
            continue
        _force(forced, small["name"], big["name"])
        if by_score or by_cv or _amplitude_tie(big, small, cv_of, tol, half):
            forced.setdefault("_ties", []).append((small["name"], big["name"]))
    if not pairs:
        return best, forced
    if not winners:
        return pairs[0][1], forced
    for big, small in winners:
        _force(forced, big["name"], small["name"])
    return min((w for w, _ in winners), key=lambda r: ranking.credited(r, credit, 1.0)), forced


def _amplitude_tie(big, small, cv_of, tol, half) -> bool:
    """Whether a nested pair whose larger family adds only an amplitude dependence
    (AMPLITUDE_NESTS) explains the data equally: both explain it (leave less than `half`, the
    residual halfway between the marker noise and the baseline, as ranking.confounded asks), the
    larger fits at least as well, and leave-one-recording-out does not prefer the smaller one
    beyond the noise."""
    if big["name"] not in AMPLITUDE_NESTS or half is None or not big["rss"] <= small["rss"] < half:
        return False
    lb, ls = cv_of(big["name"], big["_fit"]), cv_of(small["name"], small["_fit"])
    return lb is None or ls is None or lb <= ls + tol.get(big["name"], 0.0)


def _force(forced, winner, loser):
    """Record "winner beats loser" in `forced` (a single loser as a name, several as a list)."""
    have = forced.get(winner)
    if have is None:
        forced[winner] = loser
    elif loser not in ([have] if isinstance(have, str) else have):
        forced[winner] = ([have] if isinstance(have, str) else list(have)) + [loser]


def _nested_evidence(big, small, cv_of, credit, tol, say, floor_wide):
    """(by the credited criterion, by leave-one-recording-out): whether each prefers the larger
    family `big` of a nested pair to the smaller `small` (see _resolve_nested)."""
    lb, ls = cv_of(big["name"], big["_fit"]), cv_of(small["name"], small["_fit"])
    # the extra parameters of the larger family may fit discretisation error on top of what the
    # smaller one does: its criterion is charged all it can mimic of that error (its credit,
    # ranking.py, at face value, not CREDIT_FACTOR times it as between unrelated families: a
    # located region's credit is already scaled to the conservative floor, all the mesh error
    # the data can hold, and 2.5x that asked a region to gain more than any mimicry could; a
    # true region was never preferred), and its cross-validation must agree. (A located region
    # is kept fixed here: re-locating it per fold from the other recording alone was tried and
    # is too poor with two train recordings, e.g. the named heterogeneity bar 0.31 vs 0.13.)
    gain = small["rss"] - big["rss"]
    crit = big.get("_criterion")
    if big["name"] in OFFSET_NESTS and crit is not None:
        # its discretisation offset is a free stiffness scale inside its range: a parameter of the
        # comparison with the uniform scale, not a nuisance
        big = dict(big, _criterion=(crit[0] + 1,) + tuple(crit[1:]))
    by_score = ranking.credited(big, credit, 1.0) < ranking.credited(small, credit, 1.0)
    # A family that picks its place from the data (a located region: FAMILIES extra_dof) has a
    # credit measured on the refined-mesh discrepancy's pattern only; the truth's own mesh error,
    # in another pattern, it can follow just as well. Where the smaller family leaves no more
    # than the conservative floor, all that is left may be such error: the located family is
    # then not preferred (stiffer bars and capsules whose region gained 1.5-3x its credit over
    # the uniform scale: r2_03, the 1-2 tets across test bar). Families whose pattern the
    # physics fixes keep their measured credit (named strain-dependent damping bar).
    if floor_wide is not None and FAMILIES[big["name"]].extra_dof > 0 and small["rss"] <= floor_wide:
        by_score = False
    # a leave-one-recording-out difference within the noise fluctuation is no evidence
    by_cv = by_score if lb is None else lb < ls - tol.get(big["name"], 0.0)
    say(f"nested {big['name']} vs {small['name']}: score {big['score']:.1f} vs {small['score']:.1f}, "
        f"rss gain {gain:.3e} (credit {credit.get(big['name'], 0):.3e}), "
        f"leave-one-recording-out rss {lb} vs {ls}")
    return by_score, by_cv


def _at_support(region, clamp_layer, tets) -> bool:
    """A located region lies at the support when most of its elements are within one element
    layer of the clamp (share a vertex with the clamp layer's elements)."""
    if region is None or clamp_layer is None or not np.any(region) or not np.any(clamp_layer):
        return False
    tets = np.asarray(tets)
    near = np.isin(tets[region], np.unique(tets[clamp_layer])).any(axis=1)
    return bool(near.mean() >= 0.5)


def _support_or_region(ranked, ctx, say):
    """A stiffness change at the clamp is described by two families: the clamp layer's scale
    (support_compliance) and a located region touching the clamp (heterogeneity); the data
    barely tell them apart. The physics does: a support can only add compliance to the rigid
    clamp of the nominal model, so
    * a clamp layer fitted *stiffer* than the body is a stiffer material near the clamp, not a
      compliant support: where it leads and a located region explains the data as well
      (confounded), the region leads;
    * a located region that lies at the support (`_at_support`) and is *softer* than the rest,
      with the clamp layer also fitted softer, is a compliant support whose soft layer the
      model's clamp-layer elements do not match (thinner or partial): the support leads, the
      region is reported as equally explaining (confounded).
    Moves the new lead to the front of `ranked`; returns {winner: loser} for the ordering (each
    also recorded as a tie, so both names carry confounded_with)."""
    rows = {r["name"]: r for r in ranked}
    S, H = rows.get("support_compliance"), rows.get("heterogeneity")
    if not ranked or S is None or H is None or S["_fit"] is None or H["_fit"] is None:
        return {}
    t_s = float(np.asarray(S["_fit"].params.get("support_compliance", [0.0]), float)[0])
    t_h = np.asarray(H["_fit"].params.get("heterogeneity", [0.0, 0.0]), float)
    t_h = np.append(t_h, 0.0)[:2] if t_h.size < 2 else t_h
    out = {}
    if ranked[0] is S and t_s > 0 and "heterogeneity" in S.get("confounded_with", []):
        out = {"heterogeneity": "support_compliance"}
        lead = H
    elif (ranked[0] is H and t_s < 0 and t_h[0] < t_h[1]
          and _at_support(ctx.region, ctx.clamp_layer, ctx.mesh.tets)):
        out = {"support_compliance": "heterogeneity"}
        lead = S
    if out:
        ranked.remove(lead)
        ranked.insert(0, lead)
        say(f"support vs region at the clamp: clamp layer log scale {t_s:.2f}, region/rest "
            f"{t_h[0]:.2f}/{t_h[1]:.2f}: {lead['name']} leads")
    return out


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
            if NUISANCE in r["_fit"].params and NUISANCE not in start:
                names.append(NUISANCE)
                start[NUISANCE] = r["_fit"].params[NUISANCE]
            fit = fitting.refine(P, ctx, names, start, iterations=2, progress=say)
            if best is None or fit.rss < best.rss:
                best = fit
        if best is None or best.rss + floor > ADD_FACTOR * (selected.rss + floor):
            break
        added = [n for n in best.params if n not in verdict and n != NUISANCE][0]
        verdict.append(added)
        selected = best
    return selected


# Families of the two kinds a combined truth mixes: one acts on the elastic stress, the other on
# the dissipation. A single family of one kind can mimic such a pair (a strong softening in
# tension took a stiffness change plus some of a damping change: the named combined capsule),
# and forward selection, which only adds to the lead, never meets the pair.
ELASTIC = ("stiffness_scale", "tension_nonlinearity", "compression_nonlinearity", "poisson_ratio",
           "support_compliance", "heterogeneity")
DISSIPATIVE = ("rayleigh_damping", "strain_dependent_damping")


def _joint_fit(P, ctx, a, b, say):
    """Two ranked families fitted jointly: from each member's own optimum with the other at its
    nominal value (each single optimum also absorbed what it could of the other's effect: their
    sum overshoots), the better of the two refits (a member without a simulated fit gives no
    start)."""
    fit = None
    for one, other in ((a, b), (b, a)):
        if one["_fit"] is None:
            continue
        nominal = ({other["name"]: np.zeros(len(FAMILIES[other["name"]].parameters))}
                   if other["_fit"] is None else other["_fit"].params)
        start = {**{n: np.zeros_like(np.asarray(v, float)) for n, v in nominal.items()},
                 **one["_fit"].params}
        got = fitting.refine(P, ctx, list(start), start, iterations=2, progress=say)
        fit = got if fit is None or got.rss < fit.rss else fit
    return fit


def _charged_score(rss, names, credit, n_eff, floor) -> float:
    """Information criterion of a fit of the families `names` (one or more) with its residual
    charged CREDIT_FACTOR x the sum of their discretisation credits (at most all the mesh's
    error, ranking.charge)."""
    rss = rss + min(sum(ranking.charge(n, credit) for n in names), ranking.cap_of(credit))
    return fitting.score(rss, sum(_dof(n) for n in names), n_eff, floor)


def _members_needed(fit, a, b, credit, tol) -> bool:
    """Each member of a jointly fitted pair adds to the other: the pair beats each member's own
    single fit by more than CREDIT_FACTOR x the other member's credit (ranking.charge) and the noise."""
    return all(fit.rss < m["rss"] - ranking.charge(o, credit) - tol.get(o, 0.0)
               for m, o in ((a, b["name"]), (b, a["name"])))


# simulated single fits (lowest residual first) whose pairs _pair_rescue fits jointly
RESCUE_TOP = 4


def _pair_rescue(P, ctx, ranked, n_eff, floor, rss0, credit, tol, say, top=RESCUE_TOP):
    """(verdict, fit) or None: where the gap is significant and no single family explains enough
    of it (the verdict would be `unexplained`), two effects of any kind may: every pair of the
    `top` simulated single fits (by residual; no family with one nested in it, no density, which
    is the stiffness scale's mirror) is fitted jointly (_joint_fit). The pair with the best
    information criterion, every fit charged CREDIT_FACTOR x its discretisation credit, is the
    verdict when it explains EXPLAINED_MIN of the residual above the floor, each member is needed
    (_members_needed) and it beats the best single fit's criterion. Random seed 8's capsule
    r8_03 (a located stiffer region and a tension nonlinearity): the tension and region fits
    each explain 0.42 of the excess, beyond 2.5x the conservative floor."""
    rows = sorted((r for r in ranked if r["_fit"] is not None and r["name"] != "density"),
                  key=lambda r: r["rss"])[:top]
    if len(rows) < 2:
        return None
    single = min(_charged_score(r["rss"], [r["name"]], credit, n_eff, floor) for r in rows)
    order = [r["name"] for r in ranked]
    best = None
    for i, a in enumerate(rows):
        for b in rows[i + 1:]:
            names = [a["name"], b["name"]]
            if any(NESTS.get(x, (None,))[0] == y for x, y in (names, names[::-1])):
                continue
            fit = _joint_fit(P, ctx, a, b, say)
            score = _charged_score(fit.rss, names, credit, n_eff, floor)
            need = _members_needed(fit, a, b, credit, tol)
            explained = _explained_excess(fit.rss, rss0, floor)
            say(f"rescue pair {' + '.join(names)}: rss {fit.rss:.3e} (score {score:.1f}, best single "
                f"{single:.1f}), explains {explained:.2f} of the excess; each member needed {need}")
            if need and explained >= EXPLAINED_MIN and score < single and (best is None or score < best[0]):
                best = (score, sorted(names, key=order.index), fit)
    return None if best is None else (best[1], best[2])


def _pair_challenge(P, ctx, ranked, verdict, selected, n_eff, floor, credit, tol, say):
    """(verdict, selected): a single-effect verdict replaced by an elastic + dissipative pair
    that does not contain it (adding to the lead is _forward_select's decision) when the pair,
    fitted jointly from its members' single optima, beats the lead by more than the noise, by
    the information criterion with every fit charged CREDIT_FACTOR x its discretisation credit
    (the pair the sum of its members'), and when each member is needed: the pair beats each
    member's own single fit by more than the other member's credit and the noise (a family
    that adds nothing to the other is no second effect). The pairs: every simulated elastic fit
    with every simulated dissipative one (with both dissipative families, from the elastic
    optimum, where none was simulated); the member whose single fit leads the ranking comes
    first."""
    if len(verdict) != 1 or selected is None:
        return verdict, selected
    rows = {r["name"]: r for r in ranked if r["_fit"] is not None}
    lead = rows.get(verdict[0])
    if lead is None:
        return verdict, selected
    by_rss = lambda names: sorted((rows[n] for n in names if n in rows), key=lambda r: r["rss"])  # noqa: E731
    elastic, dissipative = by_rss(ELASTIC), by_rss(DISSIPATIVE)
    if not dissipative:
        # no dissipative family was simulated alone (their linear predictions gained little):
        # they join the pairs from the elastic member's optimum, each with its linear prediction
        # as its single residual (random seed 8's density + Rayleigh capsule, called a Poisson
        # ratio: the stiffness scale + damping leaves 7.1e-3 against the ratio's 2.3e-2)
        dissipative = [r for r in ranked if r["name"] in DISSIPATIVE]
    order = [r["name"] for r in ranked]
    # adding to the lead is forward selection's decision, and a family that contains the lead
    # (strain-dependent damping over Rayleigh, a region over the scale) adds to it too (random
    # seed 5's Rayleigh bar r5_09 became strain-dependent damping + clamp layer); a family
    # nested *in* the lead makes a different explanation and stays (random seed 8's tension +
    # Rayleigh and Rayleigh + support, led by strain-dependent damping)
    contains = {lead["name"]} | {big for big, (small, _) in NESTS.items() if small == lead["name"]}
    lead_score = _charged_score(lead["rss"], [lead["name"]], credit, n_eff, floor)

    def beats_lead(rss, score):
        return rss < lead["rss"] - tol.get(lead["name"], 0.0) and score < lead_score

    # the lead completed by a challenger's member of the other kind (its companion), fitted
    # jointly and cached by that member: a pair gains nothing over the lead when the lead with
    # the same companion explains the data as well (as well beyond the noise, and a criterion no
    # worse), and the completion is the candidate instead: random seed 6's soft support r6_01,
    # clamp layer 9.7e-2, became a located region + Rayleigh at 8.6e-2 while the clamp layer +
    # Rayleigh leaves 4.7e-2
    kind = ELASTIC if lead["name"] in ELASTIC else DISSIPATIVE if lead["name"] in DISSIPATIVE else None
    completed = {}

    def completion(companion):
        if companion["name"] not in completed:
            got = _joint_fit(P, ctx, lead, companion, say)
            names = [lead["name"], companion["name"]]
            completed[companion["name"]] = (got, names, _charged_score(got.rss, names, credit, n_eff, floor))
        return completed[companion["name"]]

    best = None
    for e in elastic:
        for d in dissipative:
            names = [e["name"], d["name"]]
            if contains & set(names):
                continue
            fit = _joint_fit(P, ctx, e, d, say)
            score = _charged_score(fit.rss, names, credit, n_eff, floor)
            need = _members_needed(fit, e, d, credit, tol)
            beats = beats_lead(fit.rss, score)
            say(f"pair {e['name']} + {d['name']}: rss {fit.rss:.3e} (score {score:.1f}) vs lead "
                f"{lead['name']} {lead['rss']:.3e} (score {lead_score:.1f}); each member needed {need}, "
                f"beats the lead {beats}")
            # the member the lead's completion replaces, and the companion it keeps
            same, companion = (e, d) if kind is ELASTIC else (d, e)
            if need and beats and kind is not None and NESTS.get(lead["name"], (None,))[0] != same["name"]:
                # (a lead that contains that member, strain-dependent damping over Rayleigh, has
                # a completion containing the pair: which of the two is right is the nested
                # families' question, decided on the single fits; random seed 8's tension +
                # Rayleigh r8_04, led by strain-dependent damping, is `[rayleigh_damping,
                # support_compliance]` by the pair, the damping of the truth)
                r_fit, r_names, r_score = completion(companion)
                tied = r_fit.rss <= fit.rss + tol.get(lead["name"], 0.0) and r_score <= score
                say(f"pair {e['name']} + {d['name']} against the lead with the same companion "
                    f"({' + '.join(r_names)}: rss {r_fit.rss:.3e}, score {r_score:.1f}): "
                    f"{'as good: the completed lead is the candidate' if tied else 'the pair is better'}")
                beats = not tied
                # the completed lead is then the pair the data prefer, held to the same bar as
                # any pair (beats the lead, each member needed): the named plastic set
                # history_plasticity's compression + damping pair, which replaced a tension lead,
                # is tension + Rayleigh (6.5e-2 against 7.8e-2), and the history model is
                # measured against it
                if (tied and beats_lead(r_fit.rss, r_score) and _members_needed(r_fit, lead, companion, credit, tol)
                        and (best is None or r_score < best[0])):
                    best = (r_score, sorted(r_names, key=order.index), r_fit)
            if need and beats and (best is None or score < best[0]):
                best = (score, sorted(names, key=order.index), fit)
    if best is None:
        return verdict, selected
    return best[1], best[2]
