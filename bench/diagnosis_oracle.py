"""How far could a perfect diagnosis shrink the held-out gap on the model's own mesh?

For every built case of bench/diagnosis_independent.py (a folder with scene.toml, truth.json and
the diagnosis it ran, diag/diagnosis.json) the held-out (test) gap is replayed, with the same
scoring as `matlearn diagnose` (fitting.gap, % of the object size), for:

* the nominal model (the diagnosis' own gap_before, read from its diagnosis.json);
* the nominal model with the mesh's stiffness offset the diagnosis applied (no effect);
* the *true* effect carried onto the model's mesh with the mesh's stiffness offset refitted to
  the train recordings inside the diagnosis' plausible range (the "oracle": a diagnosis that knows
  the effect and its size), and the lowest gap of the true effect over that range (a bound that
  even chooses the offset on the test recording itself);
* what the diagnosis reached (its verdict's gap_after; gap_before for an empty verdict).

The true effect on the model mesh: a stiffness or density factor, the truth's Rayleigh
coefficients or alpha_K polynomial, the truth's designed law with its stress bump (tension /
compression), the truth's region (model tets whose centroid lies in its sphere) with its factor.
A soft pad behind the clamp (support compliance) is geometry the model does not have: no oracle.
What the oracle leaves is the model mesh's discretisation error and the test recording's own
start estimate: a diagnosis naming the right effect cannot shrink the gap below it, so the
oracle's median shrink bounds what the suites' `median_gap_shrink` target can reach.

    python bench/diagnosis_oracle.py --work /tmp/w_i11 /tmp/w_i12 /tmp/w_i13 --out bench/results/diagnosis_oracle.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import code_commit  # noqa: E402

OFFSET_SCAN = 5  # offsets tried across the diagnosis' plausible range for the bound


def true_model(scene, truth: dict, offset: float):
    """The model mesh's model with the truth's effect(s) carried over and the stiffness offset
    `offset` (a factor on E); None where an effect has no counterpart on the model (a pad)."""
    from matlearn.materials import Damping, Material

    mat, damp = scene.material, scene.damping
    E = np.asarray(mat.youngs_modulus, float) * offset
    rho, law, edits = mat.density, mat.model, list(mat.edits)
    p = truth.get("params", {})
    for eff in truth["effects"]:
        if eff == "stiffness_scale":
            E = E * p["stiffness_factor"]
        elif eff == "density":
            rho = float(rho) * p["density_factor"]
        elif eff == "rayleigh_damping":
            d = p["truth_damping"]
            damp = Damping(d["alpha_mass"], d["alpha_stiffness"])
        elif eff == "strain_dependent_damping":
            damp = Damping(damp.alpha_mass, damp.alpha_stiffness, stiffness_poly=list(p["stiffness_poly"]))
        elif eff in ("tension_nonlinearity", "compression_nonlinearity"):
            law, edits = "designed", [tuple(e) for e in p["edits"]]
        elif eff == "heterogeneity":
            V = np.asarray(scene.mesh.vertices)
            C = V[np.asarray(scene.mesh.tets)].mean(axis=1)
            inside = np.linalg.norm(C - np.asarray(p["region_centre"]), axis=1) < p["region_radius"]
            E = np.broadcast_to(E, (scene.mesh.num_tets,)).copy()
            E[inside] *= p["region_factor"]
        else:  # support_compliance: the truth's pad is not part of the model's geometry
            return None
    return scene.model(material=Material(law, E, mat.poisson_ratio, rho, edits), damping=damp)


def case_row(case: Path) -> dict | None:
    from matlearn.diagnosis import fitting
    from matlearn.diagnosis.pipeline import START_DECISION
    from matlearn.diagnosis.problem import Problem

    diag = case / "diag" / "diagnosis.json"
    if not (diag.exists() and (case / "truth.json").exists()):
        return None
    truth = json.loads((case / "truth.json").read_text())
    d = json.loads(diag.read_text())
    t0 = time.time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # as diagnose() builds it: each recording's start (at rest or in motion) decided from its data
        P = Problem(case / "scene.toml", estimate_velocity="auto" if START_DECISION else False)
        scene = P.scene

        def gap(model):  # None: the model cannot be simulated on the held-out motion
            try:
                return fitting.gap(P, model)["max_error_pct"]
            except RuntimeError:
                return None

        disc = d["discretisation"]
        k = disc["stiffness_factor"]
        lo, hi = disc["factor_range"]

        def train_rss(model):  # raw: this Problem has no discretisation discrepancy to remove
            r = fitting.marker_residual(P, model)
            return float(r @ r)

        factors = sorted(set(np.geomspace(lo, hi, OFFSET_SCAN).tolist() + [k]))
        models = [true_model(scene, truth, f) for f in factors]
        at_offset = best = k_oracle = None
        if models[0] is not None:
            j = int(np.argmin([train_rss(m) for m in models]))
            gaps = [gap(m) for m in models]
            k_oracle, at_offset = factors[j], gaps[j]
            best = min((g for g in gaps if g is not None), default=None)
    before = d["gap_before"]["max_error_pct"]
    verdict = d["verdict"]
    reached = before
    if verdict and verdict != ["unexplained"]:
        got = [e.get("gap_after") for e in d["effects"] if e["name"] == verdict[-1]]  # cumulative
        if got and got[0]:
            reached = got[0]["max_error_pct"]
    return {"case": case.name, "suite": case.parent.name, "true_effects": truth["effects"], "verdict": verdict,
            "gap_before_pct": before, "gap_with_offset_pct": (disc.get("gap_with_offset") or {}).get("max_error_pct"),
            "oracle_gap_pct": at_offset, "oracle_best_offset_gap_pct": best, "diagnosis_gap_after_pct": reached,
            "stiffness_offset": k, "oracle_stiffness_offset": k_oracle, "wall_s": time.time() - t0}


def shrink(before, after):
    return None if before is None or after is None or before <= 0 else max(0.0, 1.0 - after / before)


def summary(rows) -> dict:
    eff = [r for r in rows if r["true_effects"]]

    def med(key, rows):
        v = [x for x in (shrink(r["gap_before_pct"], r[key]) for r in rows) if x is not None]
        return (float(np.median(v)) if v else None), len(v)

    out = {}
    for key in ("oracle_gap_pct", "oracle_best_offset_gap_pct", "diagnosis_gap_after_pct", "gap_with_offset_pct"):
        out[f"median_shrink_{key.removesuffix('_pct')}"], out[f"cases_{key.removesuffix('_pct')}"] = med(key, eff)
    # the diagnosis on the cases that have an oracle (without the clamp pads)
    out["median_shrink_diagnosis_where_oracle"] = med(
        "diagnosis_gap_after_pct", [r for r in eff if r["oracle_gap_pct"] is not None])[0]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", nargs="+", required=True, help="built independent-suite folders")
    ap.add_argument("--out", default=None, help="JSON to write")
    a = ap.parse_args(argv)
    rows = []
    print(f"{'suite':>8s} {'case':16s} {'true effects':36s} {'before':>7s} {'offset':>7s} {'oracle':>7s} "
          f"{'bound':>7s} {'reached':>7s}")
    fmt = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    for folder in a.work:
        for case in sorted(p for p in Path(folder).iterdir() if p.is_dir()):
            r = case_row(case)
            if r is None:
                continue
            rows.append(r)
            print(f"{r['suite'][-8:]:>8s} {r['case'][:16]:16s} {','.join(r['true_effects'])[:36]:36s} "
                  f"{fmt(r['gap_before_pct']):>7s} {fmt(r['gap_with_offset_pct']):>7s} {fmt(r['oracle_gap_pct']):>7s} "
                  f"{fmt(r['oracle_best_offset_gap_pct']):>7s} {fmt(r['diagnosis_gap_after_pct']):>7s}", flush=True)
    by_suite = {s: summary([r for r in rows if r["suite"] == s]) for s in dict.fromkeys(r["suite"] for r in rows)}
    tot = summary(rows)
    for s, v in list(by_suite.items()) + [("all", tot)]:
        print(f"{s}: median shrink, oracle {fmt(v['median_shrink_oracle_gap'])}, bound "
              f"{fmt(v['median_shrink_oracle_best_offset_gap'])}, diagnosis {fmt(v['median_shrink_diagnosis_gap_after'])} "
              f"(where an oracle exists {fmt(v['median_shrink_diagnosis_where_oracle'])}), the mesh's stiffness "
              f"factor alone {fmt(v['median_shrink_gap_with_offset'])}")
    if a.out:
        Path(a.out).write_text(json.dumps({"commit": code_commit(), "cases": rows, "by_suite": by_suite,
                                           "totals": tot}, indent=1) + "\n")


if __name__ == "__main__":
    main()
