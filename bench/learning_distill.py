"""Benchmark: distillation of a learned RBF correction into the 6-6-6-3 MLP (method.md 6).

Uses the runs of bench/learning_table.py (default work folder): for each given case, samples
(Fh, Fhdot) -> total correction from simulations with the RBF model (train motions at 0.5x, 1x,
1.5x their initial poses), trains the MLP, and reports NN-vs-RBF agreement on those samples, the
evaluation-speed ratio (RBF time / MLP time, same inputs and process, best of 5), and the
held-out test error of both models. Writes bench/results/learning_distill.json.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import argparse
import json
from pathlib import Path

import numpy as np

from matlearn.learning.distill import compare, simulation_samples, train_mlp
from matlearn.learning.fit import RbfParams
from matlearn.learning.io import mlp_correction
from matlearn.learning.loop import Learner
from matlearn.replay import score
from matlearn.scene import load_scene

OUT = Path(__file__).parent / "results" / "learning_distill.json"


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", default="bar_damping_2,sphere_tension")
    ap.add_argument("--work", default="/tmp/matlearn_learning_bench")
    args = ap.parse_args()
    rows = []
    for name in args.cases.split(","):
        scene = load_scene(Path(args.work) / "cases" / name / "scene.toml")
        lr = Learner(scene, Path(args.work) / "runs" / name, log=None)
        lr._load_resume()
        res = lr.finish()
        params: RbfParams = res["params"]
        if params is None:
            continue
        rbf = params.correction()
        X, Y = simulation_samples(scene, rbf, scene.recordings_with_role("train"))
        mlp, info = train_mlp(X, Y)
        mc = mlp_correction(mlp)
        cmp = compare(rbf, mc, X, Y)
        try:
            mlp_test = [r["max_error_pct"] for r in score(scene, scene.model(mc), "test")["recordings"]]
        except RuntimeError as err:
            mlp_test = str(err)
        rbf_test = res["final"]["test"]["per_recording_max_pct"]
        rows.append({"case": name, **info, **cmp, "rbf_centers": int(len(params.centers)),
                     "rbf_max_error_pct_test": rbf_test, "mlp_max_error_pct_test": mlp_test})
        print(json.dumps(rows[-1], indent=1), flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps({"cases": rows}, indent=1))
    print(f"{'case':18s} {'rel err':>8s} {'speed RBF/MLP':>14s} {'RBF test':>14s} {'MLP test':>14s}")
    for r in rows:
        f = lambda v: "/".join(f"{x:.2f}" for x in v) if isinstance(v, list) else "failed"  # noqa: E731
        print(f"{r['case']:18s} {r['relative_error']:8.3f} {r['speed_ratio_rbf_over_mlp']:14.2f} "
              f"{f(r['rbf_max_error_pct_test']):>14s} {f(r['mlp_max_error_pct_test']):>14s}")


if __name__ == "__main__":
    main()
