"""Learning at scale (issue 3's timing target): one learning iteration on a ~5k-tet bar with a
1 s recording at 1 ms steps, timed stage by stage, beside one forward simulation of the same
recording measured in the same run (the reference: ratios are meaningful on a loaded machine).

Case: a 0.2 m x 0.04 m x 0.04 m bar (`meshes.bar_with_tets`, --tets), truth neo-Hookean
E = 1 MPa, nominal co-rotated E = 1.2 MPa, Rayleigh alpha_K = 0.005, clamped at x = 0, released
from a 1 N tip load; train recording --duration s with markers on --marker-fraction of the
surface vertices at --frame-rate Hz; the simulation (and space-time) runs at 1 ms.

Stages (the loop's own functions, in the order `learn` calls them):
  forward_sim      nominal forward simulation of the train recording + marker error (the loop's
                   error evaluation; also the reference)
  initial_traj     marker-following constrained simulation (first iteration only)
  pod              POD basis from the forward simulation and the initial trajectory
  spacetime        problem set-up + Gauss-Newton solve (C++), control forces
  fit              RBF correction fit (one ridge weight)
  forward_check    forward simulation with the new correction (accept / backtrack decision)
A full run of n iterations costs about forward_sim + initial_traj + n x (pod + spacetime +
n_ridges x (fit + forward_check)); the JSON gives the single-iteration cost and that estimate.

Writes bench/results/learning_scale.json: {"tets", "vertices", "frames", "steps",
"wall_s": {stage: s}, "ratio_to_forward_sim": {...}, "one_iteration_s", "full_run_estimate_s",
"target_s", "load_avg_1min_start/end", "cpus", "omp_num_threads", ...}.

    OMP_NUM_THREADS=1 python bench/learning_scale.py [--tets 5000] [--duration 1.0] [--work DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from matlearn import meshes
from matlearn.embedding import embed_points
from matlearn.learning.fit import FitFrames, fit_correction
from matlearn.learning.initial import initial_trajectory
from matlearn.learning.loop import LearnOptions, _errors
from matlearn.learning.pod import pod_basis
from matlearn.learning.spacetime import build_problem, constrained_vertices, solve_spacetime
from matlearn.materials import Damping, Material
from matlearn.scene import load_scene
from matlearn.synthetic import Motion, make_case

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results" / "learning_scale.json"
TARGET_S = 300.0


def build(work: Path, tets: int, duration: float, frame_rate: float, fraction: float) -> Path:
    mesh = meshes.bar_with_tets(0.2, 0.04, 0.04, tets)
    name = f"bar_{mesh.num_tets}_{duration:g}s"
    if (work / name / "scene.toml").exists():
        return work / name / "scene.toml"
    tip = [[0.19, -1, -1], [1, 1, 1]]
    return make_case(work, name, mesh, Material("neo_hookean", 1e6, 0.4, 1000.0), Damping(0.0, 0.005),
                     mesh, Material("corotated", 1.2e6, 0.4, 1000.0), Damping(0.0, 0.005),
                     [[-1, -1, -1], [1e-3, 1, 1]],
                     [Motion("release", "train", duration, load={"box": tip, "force": [0.0, -1.0, 0.0]})],
                     marker_fraction=fraction, frame_rate=frame_rate, seed=0, progress=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tets", type=int, default=5000)
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--frame-rate", type=float, default=200.0)
    ap.add_argument("--marker-fraction", type=float, default=0.13)
    ap.add_argument("--work", default="/tmp/matlearn_learning_scale")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    work = Path(args.work)
    t0 = time.time()
    path = build(work, args.tets, args.duration, args.frame_rate, args.marker_fraction)
    case_s = time.time() - t0
    sc = load_scene(path)
    rec = sc.recordings_with_role("train")[0]
    emb = embed_points(sc.mesh, rec.marker_rest)
    opt = LearnOptions()
    wall, info = {}, {}

    def timed(name, fn, *a, **kw):
        t = time.time()
        out = fn(*a, **kw)
        wall[name] = time.time() - t
        print(f"{name:<15} {wall[name]:8.1f} s", flush=True)
        partial = {"benchmark": "learning_scale", "partial": True, "tets": int(sc.mesh.num_tets),
                   "recording_s": args.duration, "wall_s": wall, "case_build_s": case_s, **info,
                   "load_avg_1min_start": load0, "load_avg_1min_now": os.getloadavg()[0]}
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(partial, indent=1))
        return out

    model = sc.model()
    errs, sims = timed("forward_sim", _errors, sc, model, [rec], [emb])
    info["nominal_train_max_error_pct"] = float(errs[0].max())
    _, X0, _ = timed("initial_traj", initial_trajectory, sc, model, rec, emb)
    cons, _, _ = constrained_vertices(sc, rec)
    V = np.asarray(sc.mesh.vertices, float)
    phi = timed("pod", pod_basis, [sims[0][1], X0], V, cons, opt.modes, opt.pod_window)

    def st():
        setup = build_problem(sc, model, rec, phi, 1.0, emb)
        return solve_spacetime(setup, X0, iterations=opt.gn_iterations)
    out = timed("spacetime", st)
    rep = out["report"]
    info["spacetime"] = {"cost": [float(c) for c in rep["cost"]], "cg_iterations": list(rep["cg_iterations"]),
                         "step_length": list(rep["step_length"]), "fallback": rep.get("fallback")}
    fc = out["control_forces"]
    stride = max(1, int(np.ceil(len(fc) / opt.fit_frames)))
    frames = [FitFrames(out["X"][2::stride], out["V"][2::stride], fc[::stride], phi)]
    params, finfo = timed("fit", fit_correction, sc.model(), frames, opt.centers, damping=opt.damping,
                          ridge=opt.ridges[0], seed=opt.seed)
    info["fit_frames"] = int(finfo["frames"])
    errs2, _ = timed("forward_check", _errors, sc, sc.model(params.correction()), [rec], [emb])
    info["corrected_train_max_error_pct"] = float(errs2[0].max())
    ref = wall["forward_sim"]
    nr = len(opt.ridges)
    one = wall["pod"] + wall["spacetime"] + wall["fit"] + wall["forward_check"]
    full = wall["forward_sim"] + wall["initial_traj"] + opt.iterations * (
        wall["pod"] + wall["spacetime"] + nr * (wall["fit"] + wall["forward_check"]))
    doc = {"benchmark": "learning_scale", "tets": int(sc.mesh.num_tets), "vertices": int(sc.mesh.num_vertices),
           "frames": int(len(out["X"])), "steps": int(len(out["X"]) - 1), "time_step_s": sc.time_step,
           "recording_s": args.duration, "recording_frames": int(rec.num_frames),
           "markers": int(rec.num_markers), "modes": int(phi.shape[1]),
           "wall_s": wall, "ratio_to_forward_sim": {k: v / ref for k, v in wall.items()},
           "first_iteration_s": wall["forward_sim"] + wall["initial_traj"] + one,
           "one_iteration_s": one,
           "full_run_estimate_s": full, "full_run_estimate_note":
               f"forward_sim + initial_traj + {opt.iterations} x (pod + spacetime + {nr} x (fit + forward_check)), "
               "the defaults of LearnOptions (iterations, ridges)",
           "target_s": TARGET_S, "case_build_s": case_s, **info,
           "load_avg_1min_start": load0, "load_avg_1min_end": os.getloadavg()[0], "cpus": os.cpu_count(),
           "omp_num_threads": os.environ.get("OMP_NUM_THREADS")}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(doc, indent=1))
    print(f"\n{doc['tets']} tets, {doc['frames']} frames (load {load0:.1f} -> {doc['load_avg_1min_end']:.1f} "
          f"on {doc['cpus']} cpus)")
    print(f"{'stage':<15} {'wall s':>8} {'x forward sim':>14}")
    for k, v in wall.items():
        print(f"{k:<15} {v:8.1f} {v / ref:14.2f}")
    print(f"one iteration {one:.1f} s; first iteration {doc['first_iteration_s']:.1f} s; full run estimate "
          f"{full:.1f} s (target {TARGET_S:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
