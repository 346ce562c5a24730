"""Withheld-effect benchmark for `matlearn diagnose` (issue 5).

For every effect of the vocabulary a synthetic case whose truth has it (simulated on a finer mesh
than the model's, so a discretisation gap exists as with real data), a control case without any
effect and two cases combining two effects; the cases (shapes, truths, lab-like release / drop /
tap motions) are defined in bench/diagnosis_suite_cases.py. Nothing in matlearn.diagnosis is told the
effect or tuned to a case.

    python bench/diagnosis_suite.py [--work DIR] [--only NAME ...] [--fresh] [--rediagnose]
    python bench/diagnosis_suite.py --set random --seed N [--cases K]   # a second, random set
    python bench/diagnosis_suite.py --timing                            # one ~3k-tet diagnosis

Writes bench/results/diagnosis_suite.json (named set) or diagnosis_suite_random.json (random
set, seed 1; diagnosis_suite_random_N.json for seed N): {"cases": [{case, true_effects, verdict, top1_correct, region_iou, gap_before_pct,
gap_after_pct, wall_s, ...}], "totals": {...}}. Per-case results are cached in the work folder,
so an interrupted run resumes. --timing adds totals.timing_3k (s) to diagnosis_suite.json.

top1_strict (and totals.top1_strict_accuracy): the verdict's first effect is a true effect (for
the control: the verdict is []). top1_correct (more generous): the verdict's first effect is a
true effect, or a true effect is listed in its `confounded_with` (density and stiffness scale
cannot be told apart when every load is gravity or a prescribed motion); for the control case:
the verdict is []. gap_*_pct: held-out max error,
% of object size, before and after the verdict's effects were added. effect_pct (extra): the
effect's own size, max marker distance between the truth's test recording and its effect-free
twin's (% of object size; compare with the control's gap, the discretisation).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

# 2 cores shared by several jobs: threaded BLAS (CHOLMOD's supernodal factorisations) spins and
# runs up to ~10x slower under load; one thread per process.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402

from diagnosis_scoring import median_refined_shrink, refined_mesh_gap  # noqa: E402
from matlearn.diagnosis import diagnose
from matlearn.materials import Damping, Material
from matlearn.scene import vertices_in_box
from matlearn.synthetic import make_case

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
from provenance import code_commit  # noqa: E402
from diagnosis_suite_cases import (NOMINAL_DAMPING, build_motions, build_truth, make_shape,  # noqa: E402
                             named_specs, random_specs)

RETRY_STEPS = (12, 5, 20, 8)  # the truth's static hold is sensitive to its load increments


def build_case(work: Path, name: str, spec: dict, seed: int, reuse: bool = True) -> tuple[Path, np.ndarray | None]:
    """Write case `work/name/` (scene.toml, recordings, truth.json); return (scene path, model
    elements of the true heterogeneity region or None)."""
    model_mesh, truth_mesh, clamp, tip, axis, length = make_shape(spec["shape"])
    truth_mat, truth_damping, correction, region_model = build_truth(spec, truth_mesh, model_mesh, axis, clamp)
    if reuse and (work / name / "scene.toml").exists():
        return work / name / "scene.toml", region_model
    nominal = Material("corotated", spec["E0"], spec["nu0"], spec["rho0"])
    rng = np.random.default_rng(seed)
    fixed = vertices_in_box(np.asarray(truth_mesh.vertices), clamp)
    motions = build_motions(spec, truth_mesh, Material("corotated", spec["E0"], spec["nu0"], spec["rho0"]),
                            fixed, tip, axis, length, rng)
    extra = {"spec": spec, "region_model": region_model}
    for steps in RETRY_STEPS:
        for m_ in motions:
            m_.load_steps = steps
        try:
            path = make_case(work, name, truth_mesh, truth_mat, truth_damping, model_mesh, nominal,
                             Damping(*NOMINAL_DAMPING), clamp, motions, marker_fraction=0.25,
                             noise=3e-5, seed=seed, truth_correction=correction, extra=extra)
            return path, region_model
        except RuntimeError as err:
            print(f"{name}: truth hold failed with {steps} load steps ({err})", file=sys.stderr)
            if "history_dependence" in spec["effects"]:  # stateful truth: start afresh
                truth_mat, truth_damping, correction, _ = build_truth(spec, truth_mesh, model_mesh, axis, clamp)
    raise RuntimeError(f"{name}: the truth's static hold failed for every load-step count")


def effect_size(work: Path, name: str, spec: dict, seed: int) -> float | None:
    """How visible the case's effect is: max marker distance (% of the model's object size)
    between the test recordings of the truth and of its effect-free twin (same fine mesh,
    markers, motions; nominal material, no noise). Compare with the control case's nominal gap
    (the discretisation). Cached in work/name/twin/; None for the control."""
    if not spec["truth"]:
        return None
    from matlearn import meshes
    from matlearn.recording import load_recording

    twin_dir = work / name / "twin"
    if not (twin_dir / "test_0.npz").exists():
        model_mesh, truth_mesh, clamp, tip, axis, length = make_shape(spec["shape"])
        plain = dict(spec, truth={})
        mat, damping, _, _ = build_truth(plain, truth_mesh, model_mesh, axis, clamp)
        fixed = vertices_in_box(np.asarray(truth_mesh.vertices), clamp)
        motions = build_motions(spec, truth_mesh, mat, fixed, tip, axis, length, None)
        tests = [m for m in motions if m.role == "test"]
        nominal = Material("corotated", spec["E0"], spec["nu0"], spec["rho0"])
        make_case(work / name, "twin", truth_mesh, mat, damping, model_mesh, nominal, damping, clamp, tests,
                  marker_fraction=0.25, noise=0.0, seed=seed)
    size = meshes.object_size(make_shape(spec["shape"])[0])
    worst = 0.0
    for i, _ in enumerate(m for m in spec["motions"] if m[1] == "test"):
        a = load_recording(work / name / f"test_{i}.npz").markers
        b = load_recording(twin_dir / f"test_{i}.npz").markers
        worst = max(worst, float(np.nanmax(np.linalg.norm(a - b, axis=2))))
    return 100.0 * worst / size


def _commit() -> str:
    """The code a row was measured with (provenance.code_commit over the diagnosis code)."""
    return code_commit(("python/matlearn/diagnosis",))

def iou(a, b) -> float:
    a, b = set(map(int, a)), set(map(int, b))
    return len(a & b) / max(len(a | b), 1)


def score_case(name, spec, result, region_model, wall):
    verdict = result["verdict"]
    true = spec["effects"]
    strict = verdict == [] if not true else bool(verdict and verdict[0] in true)
    if not true:
        top1 = verdict == []
    elif verdict and verdict[0] in true:
        top1 = True
    else:
        first = next((e for e in result["effects"] if verdict and e["name"] == verdict[0]), {})
        top1 = bool(set(first.get("confounded_with", [])) & set(true))
    region_iou = None
    if region_model is not None:
        regions = result["where"]["regions"]
        region_iou = iou(regions[0]["elements"], region_model) if regions else 0.0
    before = result["gap_before"]["max_error_pct"]
    with_gap = {e["name"]: e for e in result["effects"] if e.get("gap_after")}
    applied = [v for v in verdict if v in with_gap]
    after = with_gap[applied[-1]]["gap_after"]["max_error_pct"] if applied else before
    return {"case": name, "true_effects": true, "verdict": verdict, "top1_correct": bool(top1),
            "top1_strict": bool(strict),
            "region_iou": region_iou, "gap_before_pct": before, "gap_after_pct": after,
            "gap_refined_mesh_pct": refined_mesh_gap(result), "wall_s": wall}


def _strict(row) -> bool:
    v = row.get("verdict")
    if not row["true_effects"]:
        return v == []
    return bool(v and v[0] in row["true_effects"])


def totals(rows):
    # a case whose random truth could not be simulated (build_case failed) has nothing to
    # diagnose: listed in truth_failed_cases, not scored
    unbuilt = [r["case"] for r in rows if r.get("truth_failed")]
    rows = [r for r in rows if not r.get("truth_failed")]
    eff = [r for r in rows if r["true_effects"]]
    ctrl = [r for r in rows if not r["true_effects"]]
    shrink = [1 - r["gap_after_pct"] / r["gap_before_pct"] for r in eff if r["gap_before_pct"]]
    ious = [r["region_iou"] for r in rows if r["region_iou"] is not None]
    return {
        "cases": len(rows),
        "top1_accuracy": float(np.mean([r["top1_correct"] for r in eff])) if eff else None,
        # verdict[0] itself a true effect (no credit for a true effect in its confounded_with)
        "top1_strict_accuracy": float(np.mean([_strict(r) for r in eff])) if eff else None,
        "top1_strict_all_cases": f"{sum(_strict(r) for r in rows)}/{len(rows)}",
        "control_clean": all(r["verdict"] == [] for r in ctrl),
        "failed_cases": [r["case"] for r in rows if r.get("error")],
        "truth_failed_cases": unbuilt,
        "mean_region_iou": float(np.mean(ious)) if ious else None,
        "median_gap_shrink": float(np.median(shrink)) if shrink else None,
        "median_gap_shrink_refined_mesh": median_refined_shrink(rows),
        "total_wall_s": float(sum(r["wall_s"] for r in rows)),
        "max_wall_s": float(max(r["wall_s"] for r in rows)) if rows else None,
    }


def run_set(specs: dict, work: Path, names, fresh: bool, rediagnose: bool, seed0: int = 100,
            collect: bool = False):
    rows = []
    for i, name in enumerate(names):
        spec = specs[name]
        cache = work / name / "suite_row.json"
        if collect and not cache.exists():
            print(f"{name}: not run yet (--collect)", file=sys.stderr)
            continue
        seed = seed0 + list(specs).index(name)
        if cache.exists() and not (fresh or rediagnose):
            row = json.loads(cache.read_text())
            if "effect_pct" not in row:
                row["effect_pct"] = effect_size(work, name, spec, seed)
                cache.write_text(json.dumps(row))
            rows.append(row)
            print(f"{name}: cached", file=sys.stderr)
            continue
        print(f"== {name} ({i + 1}/{len(names)}): building truth", file=sys.stderr, flush=True)
        t0 = time.time()
        built = False
        try:
            path, region_model = build_case(work, name, spec, seed=seed, reuse=not fresh)
            built = True
            t0 = time.time()
            result = diagnose(path, work / name / "diagnosis", seed=0,
                              report=(name in ("heterogeneity",)))
            row = score_case(name, spec, result, region_model, time.time() - t0)
        except (RuntimeError, ValueError) as err:  # a failed case is reported, not hidden
            row = {"case": name, "true_effects": spec["effects"], "verdict": None,
                   "top1_correct": False, "region_iou": None, "gap_before_pct": None,
                   "gap_after_pct": None, "wall_s": time.time() - t0, "error": str(err)}
            if not built:  # the random truth itself could not be simulated: no case to diagnose
                row["truth_failed"] = True
                row["error"] = f"truth could not be built: {err}"
        try:
            row["effect_pct"] = effect_size(work, name, spec, seed) if built else None
        except (RuntimeError, ValueError, OSError) as err:
            row["effect_pct"] = None
            print(f"{name}: effect size failed ({err})", file=sys.stderr)
        row["shape"] = spec["shape"]["kind"]
        row["motions"] = [m[0] for m in spec["motions"]]
        row["commit"] = _commit()
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps(row))
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def print_table(rows):
    print(f"{'case':40s} {'shape':8s} {'true':42s} {'verdict':42s} top1 iou   effect before after  wall")
    for r in rows:
        if r.get("error"):
            print(f"{r['case']:40s} FAILED: {r['error']}")
            continue
        iou_s = "-" if r["region_iou"] is None else f"{r['region_iou']:.2f}"
        print(f"{r['case']:40s} {r.get('shape', ''):8s} {','.join(r['true_effects']):42s} "
              f"{','.join(r['verdict']):42s} {'yes' if r['top1_correct'] else 'no ':4s} {iou_s:5s} "
              f"{'-' if r.get('effect_pct') is None else format(r['effect_pct'], '6.2f'):>6s} "
              f"{r['gap_before_pct']:6.2f} {r['gap_after_pct']:6.2f} {r['wall_s']:5.0f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="case folder (default bench/work/diagnosis_suite[_random_N])")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--fresh", action="store_true", help="rebuild cases and rediagnose")
    ap.add_argument("--rediagnose", action="store_true", help="keep built cases, rediagnose")
    ap.add_argument("--collect", action="store_true",
                    help="write the results from the cached rows only (cases not run are listed)")
    ap.add_argument("--results", default=None, help="results file (default bench/results/diagnosis_suite[_random].json)")
    ap.add_argument("--set", choices=("named", "random"), default="named")
    ap.add_argument("--seed", type=int, default=1, help="seed of the random set")
    ap.add_argument("--cases", type=int, default=10, help="size of the random set")
    ap.add_argument("--build-only", action="store_true",
                    help="build the cases (truth recordings, effect sizes) without diagnosing them")
    ap.add_argument("--timing", action="store_true",
                    help="time one diagnosis of a ~3k-tet model with two recordings")
    args = ap.parse_args(argv)
    if args.timing:
        from diagnosis_timing import run_timing

        return run_timing(Path(args.work) if args.work else ROOT / "work" / "diagnosis_timing",
                          ROOT / "results" / "diagnosis_suite.json", fresh=args.fresh)
    if args.set == "random":
        specs = random_specs(args.seed, args.cases)
        work = Path(args.work) if args.work else ROOT / "work" / f"diagnosis_suite_random_{args.seed}"
        suffix = "" if args.seed == 1 else f"_{args.seed}"
        res = ROOT / "results" / f"diagnosis_suite_random{suffix}.json"
        seed0 = 1000 * args.seed
    else:
        specs = named_specs()
        work = Path(args.work) if args.work else ROOT / "work" / "diagnosis_suite"
        res = ROOT / "results" / "diagnosis_suite.json"
        seed0 = 100
    if args.results:
        res = Path(args.results)
    work.mkdir(parents=True, exist_ok=True)
    names = args.only or list(specs)
    unknown = [n for n in names if n not in specs]
    if unknown:
        raise SystemExit(f"unknown case(s) {unknown}; cases: {list(specs)}")
    if args.build_only:
        for name in names:
            seed = seed0 + list(specs).index(name)
            try:
                build_case(work, name, specs[name], seed=seed, reuse=not args.fresh)
            except RuntimeError as err:  # as in a full run: reported, the other cases still built
                print(f"{name}: truth could not be built ({err})", file=sys.stderr, flush=True)
                continue
            print(f"{name}: built, effect {effect_size(work, name, specs[name], seed)}", file=sys.stderr, flush=True)
        return
    rows = run_set(specs, work, names, args.fresh, args.rediagnose, seed0, args.collect)
    out = {"set": args.set, "seed": args.seed if args.set == "random" else None,
           "cases": rows, "totals": totals(rows)}
    done = {r["case"] for r in rows}
    out["totals"]["not_run"] = [n for n in names if n not in done]
    if not args.only:
        res.parent.mkdir(exist_ok=True)
        if res.exists():  # keep a timing measured separately
            old = json.loads(res.read_text()).get("totals", {})
            for key in ("timing_3k", "timing_3k_info"):
                if key in old:
                    out["totals"][key] = old[key]
        res.write_text(json.dumps(out, indent=1))
    print_table(rows)
    print(json.dumps(out["totals"], indent=1))


if __name__ == "__main__":
    main()
