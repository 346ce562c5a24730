"""Benchmark: transfer of a learned material to other shapes and meshes (issue 3, item 10).

For a few rows of the learning table (bench/learning_table.py, same protocol: the baseline fitted
for both laws, learning from the best start with every standard law fitted by its starts, 20
iterations at most) the learned model (its start
material and damping + its correction, saved as `matlearn learn` saves it) is rebuilt on a
second object of the same hidden material: another shape, meshed independently, with held-out
motions of its own. Scored there beside the nominal guess and the parameter-fitting baseline
fitted on the source (the Wang-2015 parameters transfer too). Each row also says whether the
source's train recordings determine the learned model's stress scale (learning/identify.py, the
check `matlearn learn` runs): where they do not, the model is not expected to transfer. Writes
bench/results/learning_transfer.json and prints a table.

Usage: python bench/learning_transfer.py [--cases dragon,bar_damping_2,sphere_compression]
[--work DIR] [--out FILE] [--merge PART ...]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from learning_table import BASELINE_LAWS, _git  # noqa: E402

from matlearn import cases, meshes  # noqa: E402
from matlearn.cases import _release  # noqa: E402  (the learning table's tip-load release)
from matlearn.learning import LearnOptions, save_model, transfer_score  # noqa: E402
from matlearn.learning.baseline import fit_parameters  # noqa: E402
from matlearn.learning.fit import EXTRAPOLATION_WEIGHTS  # noqa: E402
from matlearn.learning.start import STANDARD_LAWS, learn_from, model_meta, zero_params  # noqa: E402
from matlearn.replay import score  # noqa: E402
from matlearn.scene import load_scene  # noqa: E402
from matlearn.synthetic import DEFAULT_GRAVITY, Motion, make_case  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "learning_transfer.json"


def _axial(tip, amp, duration=0.3):
    kf = [[0.0, [0, 0, 0]], [0.08, [-amp, 0, 0]], [0.16, [-0.5 * amp, 0, 0]], [0.24, [0, 0, 0]]]
    return Motion("drive", "test", duration, drive={"box": tip, "keyframes": kf})


def targets():
    """{source case: (target name, mesh, clamp box, test motions, note)}: other shapes of the
    same material, meshed on their own, loaded in ways the source's training never was."""
    cap = meshes.capsule(radius=0.014, length=0.08, max_volume=(0.014 / 1.3) ** 3)
    cx0, cx1 = float(np.min(cap.vertices[:, 0])), float(np.max(cap.vertices[:, 0]))
    cap_tip = [[cx1 - 0.015, -1, -1], [1, 1, 1]]
    bar = meshes.bar(0.09, 0.028, 0.02, cells=(6, 3, 2))
    bar_tip = [[0.08, -1, -1], [1, 1, 1]]
    post = meshes.capsule(radius=0.03, length=0.05, max_volume=(0.03 / 1.8) ** 3)
    px0, px1 = float(np.min(post.vertices[:, 0])), float(np.max(post.vertices[:, 0]))
    post_top = [[px1 - 0.012, -1, -1], [1, 1, 1]]
    return {
        "dragon": ("stvk_capsule", cap, [[-1, -1, -1], [cx0 + 0.008, 1, 1]],
                   [_release("test", cap_tip, [0, 0.5, 0.2]), _release("test", cap_tip, [0, -0.3, 0.4], twist=[0.003, 0, 0])],
                   "the StVK bar's material on a TetGen capsule (r 14 mm, 108 mm long), clamped at one end"),
        "bar_damping_2": ("damping_bar_thick", bar, [[-1, -1, -1], [1e-4, 1, 1]],
                          [_release("test", bar_tip, [0, 0.35, 0.1]), _release("test", bar_tip, [0, -0.2, 0.4])],
                          "the strain-dependent damping on a shorter, wider bar (6 x 3 x 2 cells)"),
        "sphere_compression": ("compression_post", post, [[-1, -1, -1], [px0 + 0.012, 1, 1]],
                               [_axial(post_top, 0.008), _axial(post_top, 0.012)],
                               "the compression-edited material on a capsule post (r 30 mm, 110 mm "
                               "long) pushed along its axis by its keyframed top cap"),
    }


def run_case(name: str, work: Path, iterations: int, baseline_evals: int) -> dict:
    spec = next(f for f in cases.ALL if f.__name__ == name)()
    kw = spec.kwargs
    t0 = time.time()
    src = load_scene(cases.build(spec, work / "cases"))
    fits = {law: fit_parameters(src, law, max_evaluations=baseline_evals) for law in BASELINE_LAWS}
    law = min(fits, key=lambda k: fits[k]["train_rms_pct"])
    opts = LearnOptions(iterations=iterations, extrapolation=EXTRAPOLATION_WEIGHTS, **spec.learn)
    log = lambda *a: print("   ", *a, flush=True)  # noqa: E731
    _, sinfo, res, _ = learn_from(src, "best", work / "runs" / name, opts, warm=fits, laws=STANDARD_LAWS,
                                  log=log)
    params = res["params"] if res["params"] is not None else zero_params()
    # the run folder itself: a kept stiffness field names the run's homogeneous-start model
    # (RUN/start_<name>, model_meta's transfer_model), which another mesh gets (io.scene_model)
    model_dir = work / "runs" / name
    save_model(model_dir, params, None, meta={"start": "best", **model_meta(sinfo)})
    learn_wall = time.time() - t0
    check = sinfo["stress_scale"]  # learn_best_start's check of the kept model
    log(check["message"])
    tname, mesh, clamp, motions, note = targets()[name]
    path = make_case(work / "targets", tname, mesh, kw["truth_material"], kw["truth_damping"], mesh,
                     kw["nominal_material"], kw["nominal_damping"], clamp, motions,
                     marker_fraction=kw.get("marker_fraction", 1.0), seed=7,
                     gravity=kw.get("gravity", DEFAULT_GRAVITY))
    dst = load_scene(path)
    tr = transfer_score(dst, run_dir=model_dir)
    fit = fits[law]
    base_model = dst.model(material=fit["material"], damping=fit["damping"])
    per = lambda s: [r["max_error_pct"] for r in s["recordings"]]  # noqa: E731
    baseline = per(score(dst, base_model, "test"))
    learned, nominal = per(tr["learned"]), per(tr["nominal"])
    return {
        "case": name, "target": tname, "target_notes": note,
        "source_tets": int(src.mesh.num_tets), "target_tets": int(dst.mesh.num_tets),
        "visible_fraction": float(kw.get("marker_fraction", 1.0)),
        "source_max_error_pct_test": res["final"]["test"]["per_recording_max_pct"] if res["final"]["test"] else None,
        "max_error_pct_test": learned, "baseline_max_error_pct_test": baseline,
        "nominal_max_error_pct_test": nominal, "baseline_law": law, "start_chosen": sinfo.get("chosen"),
        "iterations": int(len(res["metrics"]) - 1), "learn_wall_s": learn_wall,
        "source_stress_scale": {k: check[k] for k in ("determined", "best_factor", "factors", "rms_error_pct",
                                                      "motion_rms_pct")},
        "source_stress_scale_by_recording": [{k: r[k] for k in ("file", "determined", "best_factor")}
                                             for r in check["recordings"]],
        "transfer_start": sinfo.get("transfer_start"),
        "ratio_baseline_over_learned": [b / max(a, 1e-12) for a, b in zip(learned, baseline)],
    }


def print_table(rows):
    f = lambda v: "/".join(f"{x:.2f}" for x in v)  # noqa: E731
    print(f"{'source':20s} {'target':20s} {'tets':>9s} {'nominal':>12s} {'baseline':>12s} {'learned':>12s} "
          f"{'base/learned':>13s} {'scale fixed':>11s}")
    for r in rows:
        print(f"{r['case']:20s} {r['target']:20s} {r['source_tets']:4d}>{r['target_tets']:<4d} "
              f"{f(r['nominal_max_error_pct_test']):>12s} {f(r['baseline_max_error_pct_test']):>12s} "
              f"{f(r['max_error_pct_test']):>12s} {f(r['ratio_baseline_over_learned']):>13s} "
              f"{str(r.get('source_stress_scale', {}).get('determined', '?')):>11s}")


def merge(parts, out: Path) -> int:
    docs = [json.loads(Path(p).read_text()) for p in parts]
    # each row keeps the commit of the run that produced it (parts written before rows carried it: their file's)
    rows = {c["case"]: {**c, "code_commit": c.get("code_commit", d.get("code_commit"))} for d in docs for c in d["cases"]}
    order = list(targets())
    doc = {k: v for k, v in docs[-1].items() if k != "cases"}
    doc["code_commit"] = sorted({r["code_commit"] for r in rows.values() if r.get("code_commit")})
    doc["cases"] = sorted(rows.values(), key=lambda c: order.index(c["case"]) if c["case"] in order else 99)
    out.write_text(json.dumps(doc, indent=1))
    print_table(doc["cases"])
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(targets()))
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--baseline-evals", type=int, default=20)
    ap.add_argument("--work", default="/tmp/matlearn_transfer_bench")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--merge", nargs="+", default=None)
    args = ap.parse_args()
    if args.merge:
        return merge(args.merge, Path(args.out))
    work, out = Path(args.work), Path(args.out)
    doc = {"notes": ("Max marker error per held-out recording of the TARGET object, % of its size: the "
                     "learned model (start material + correction, learned on the source case's train "
                     "recordings only, bench/learning_table.py protocol) rebuilt on another shape and mesh "
                     "of the same hidden material, beside the nominal guess and the source's fitted "
                     "parameters (baseline)."),
           "code_commit": _git("rev-parse", "--short", "HEAD"),
           "uncommitted_changes": _git("status", "--porcelain", "--", "../python", "../cpp", "."),
           "cases": []}
    for name in args.cases.split(","):
        print(f"== {name}", flush=True)
        row = run_case(name, work, args.iterations, args.baseline_evals)
        row["code_commit"] = doc["code_commit"]
        doc["cases"].append(row)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=1))
    print_table(doc["cases"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
