"""Benchmark: distillation of a learned RBF correction into the 6-6-6-3 MLP (method.md 6).

Uses the runs of bench/learning_table.py (default work folder): for each given case, samples
(Fh, Fhdot) -> total correction from simulations with the RBF model (train motions from 0.5x,
0.75x, 1x their initial poses: the range the simulations visit), trains the MLP, and reports
  * NN-vs-RBF agreement (relative L2 error) on the training samples and on held-out samples
    (other frames of the same simulations),
  * agreement of forward simulations: the max vertex-position difference between the MLP and
    the RBF model replaying every test recording, in % of the object size, and the test
    error of both models against the recordings,
  * speed: correction-evaluation time RBF / MLP on the same inputs (best of 5, same process),
    and whole forward-simulation time RBF / MLP (the correction is a small part of a step),
  * a capacity check: held-out and forward agreement of the same pipeline with 16-wide layers.
Writes bench/results/learning_distill.json.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import argparse
import json
from pathlib import Path

import time

import numpy as np

from matlearn.learning.distill import compare, simulation_samples, train_mlp
from matlearn.learning.fit import RbfParams
from matlearn.learning.io import mlp_correction
from matlearn.learning.loop import Learner
from matlearn.replay import initial_state, score, simulate_recording
from matlearn.scene import load_scene

OUT = Path(__file__).parent / "results" / "learning_distill.json"


def forward_agreement(scene, rbf, mlp) -> dict:
    """Replay every test recording with the RBF and the MLP model from the same initial state:
    max vertex-position difference (% of object size) and the simulation time ratio."""
    diffs, t_rbf, t_mlp = [], 0.0, 0.0
    m_rbf, m_mlp = scene.model(rbf), scene.model(mlp)
    for rec in scene.recordings_with_role("test"):
        state = initial_state(scene, m_rbf, rec)
        t = time.perf_counter()
        Xr = simulate_recording(scene, m_rbf, rec, state=state)[1]
        t_rbf += time.perf_counter() - t
        t = time.perf_counter()
        try:
            Xm = simulate_recording(scene, m_mlp, rec, state=state)[1]
        except RuntimeError:
            diffs.append(float("inf"))
            continue
        t_mlp += time.perf_counter() - t
        diffs.append(float(100 * np.linalg.norm(Xm - Xr, axis=2).max() / scene.object_size))
    return {"sim_max_diff_pct_test": diffs, "sim_time_ratio_rbf_over_mlp": t_rbf / max(t_mlp, 1e-12)}


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
        train_recs = scene.recordings_with_role("train")
        X, Y = simulation_samples(scene, rbf, train_recs, offset=0)
        Xh, Yh = simulation_samples(scene, rbf, train_recs, offset=2, seed=1)
        mlp, info = train_mlp(X, Y)
        mc = mlp_correction(mlp)
        cmp = compare(rbf, mc, X, Y)
        held = compare(rbf, mc, Xh, Yh)
        sim = forward_agreement(scene, rbf, mc)
        try:
            mlp_test = [r["max_error_pct"] for r in score(scene, scene.model(mc), "test")["recordings"]]
        except RuntimeError as err:
            mlp_test = str(err)
        rbf_test = res["final"]["test"]["per_recording_max_pct"]
        # Capacity check: the same pipeline with 16-wide hidden layers.
        wide, _ = train_mlp(X, Y, hidden=16)
        wc = mlp_correction(wide)
        wide_row = {"hidden16_heldout_relative_error": compare(None, wc, Xh, Yh, repeats=0)["relative_error"],
                    "hidden16_sim_max_diff_pct_test": forward_agreement(scene, rbf, wc)["sim_max_diff_pct_test"]}
        rows.append({"case": name, **info, **cmp, "heldout_relative_error": held["relative_error"],
                     "heldout_samples": held["samples"], **sim, **wide_row,
                     "rbf_centers": int(len(params.centers)),
                     "rbf_max_error_pct_test": rbf_test, "mlp_max_error_pct_test": mlp_test})
        print(json.dumps(rows[-1], indent=1), flush=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    if OUT.exists():  # keep the rows of cases not run now
        done = {r["case"] for r in rows}
        rows = [r for r in json.loads(OUT.read_text()).get("cases", []) if r["case"] not in done] + rows
    OUT.write_text(json.dumps({"cases": rows, "notes": (
        "MLP 6-6-6-3 (BN + ELU) distilled from the final RBF of bench/learning_table.py's run of "
        "each case; samples from RBF simulations of the train motions at 0.5/0.75/1x; relative "
        "error = ||MLP - RBF|| / ||RBF - mean|| on training samples and on held-out frames; "
        "sim_max_diff_pct_test: max vertex distance between MLP and RBF replays of each test "
        "recording (% of object size); speed ratios > 1 mean the MLP is faster. Timings on 2 "
        "shared, loaded cores.")}, indent=1))
    print(f"{'case':18s} {'rel err':>8s} {'held-out':>8s} {'sim diff %':>12s} {'eval RBF/MLP':>12s} "
          f"{'sim RBF/MLP':>11s} {'RBF test':>12s} {'MLP test':>12s}")
    for r in rows:
        f = lambda v: "/".join(f"{x:.2f}" for x in v) if isinstance(v, list) else "failed"  # noqa: E731
        g = lambda k: r.get(k, float("nan"))  # noqa: E731
        print(f"{r['case']:18s} {g('relative_error'):8.3f} {g('heldout_relative_error'):8.3f} "
              f"{f(r.get('sim_max_diff_pct_test')):>12s} {g('speed_ratio_rbf_over_mlp'):12.2f} "
              f"{g('sim_time_ratio_rbf_over_mlp'):11.2f} {f(r.get('rbf_max_error_pct_test')):>12s} "
              f"{f(r.get('mlp_max_error_pct_test')):>12s}")


if __name__ == "__main__":
    main()
