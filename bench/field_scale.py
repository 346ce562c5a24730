"""The stiffness-field fit at scale (learning/field.py, `learn --start field`): what its tangent
Jacobian costs against the finite-difference one on a ~5k-tet model with a 1 s recording.

Case: the 0.2 m x 0.04 m x 0.04 m bar of bench/learning_scale.py (`meshes.bar_with_tets`,
--tets), clamped at x = 0, released from a 1 N tip load (1 s at 1 ms, markers on --marker-fraction
of the surface at --frame-rate Hz); truth co-rotated with E = 2 MPa in the upper half (z > 0)
and 0.5 MPa below, nominal homogeneous E = 1 MPa (the fit starts from the nominal here, not
from a baseline fit, so the run measures the field alone).

Measured in one run (wall and process CPU seconds):
  simulation      one full-Newton simulation of the train recording and its marker residual
                  (`baseline.marker_residual_pct`): the reference of every ratio, and what a
                  finite-difference Jacobian costs per patch (k + 1 per iteration)
  tangent_pass    one TangentJacobian call: all k patch columns by forward-mode tangents of
                  the linearised replay
  fit             the whole tangent fit (`fit_stiffness_field`, --iterations at most)
plus the agreement of two tangent columns with central differences of the simulated residual
(`column_check`: relative error, the patches most and least loaded), and the fit's train rms
before and after and its upper-vs-lower log-stiffness contrast (truth log 4 = 1.39).

Writes bench/results/field_scale.json and prints a table.

    OMP_NUM_THREADS=1 python bench/field_scale.py [--tets 5000] [--duration 1.0] [--patches 128]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from matlearn.embedding import embed_points
from matlearn.learning import field
from matlearn.learning.baseline import marker_residual_pct
from matlearn.materials import Material
from learning_scale import add_case_arguments, build as scale_case, load_case
from provenance import code_commit

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results" / "field_scale.json"


def layered(mesh) -> Material:
    """The truth: co-rotated, E = 2 MPa above the bar's mid-plane (z > 0), 0.5 MPa below."""
    z = np.asarray(mesh.vertices)[np.asarray(mesh.tets)].mean(axis=1)[:, 2]
    return Material("corotated", np.where(z > 0, 2e6, 5e5), 0.4, 1000.0)


def build(work: Path, tets: int, duration: float, frame_rate: float, fraction: float) -> Path:
    return scale_case(work, tets, duration, frame_rate, fraction, prefix="layers", truth=layered,
                      nominal=Material("corotated", 1e6, 0.4, 1000.0))


def timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_case_arguments(ap)
    ap.add_argument("--patches", type=int, default=128)
    ap.add_argument("--iterations", type=int, default=8)
    ap.add_argument("--work", default="/tmp/matlearn_field_scale")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)

    sc, case_s = load_case(args, build)
    recs = sc.recordings_with_role("train")
    embs = [embed_points(sc.mesh, r.marker_rest) for r in recs]
    base = sc.material
    labels = field.patches(sc.mesh, args.patches, seed=0)
    k = int(labels.max()) + 1

    def material(q):
        return Material(base.model, np.full(sc.mesh.num_tets, float(base.youngs_modulus)) * np.exp(q[labels]),
                        base.poisson_ratio, base.density)

    def residual(q):
        return marker_residual_pct(sc, sc.model(material=material(q), damping=sc.damping), recs, embs)

    load0 = os.getloadavg()[0]
    r0, sim_w, sim_c = timed(lambda: residual(np.zeros(k)))
    print(f"{sc.mesh.num_tets} tets, {sc.mesh.num_vertices} vertices, {len(r0)} residual rows, {k} patches; "
          f"one simulation {sim_w:.1f} s wall, {sim_c:.1f} s CPU", flush=True)
    jac = field.TangentJacobian(sc, sc.damping, labels)
    J, tan_w, tan_c = timed(lambda: jac(material(np.zeros(k)), len(r0)))
    if J is None:
        print("the tangent Jacobian's rows do not match the residual's", file=sys.stderr)
        return 1
    print(f"tangent pass ({k} columns) {tan_w:.1f} s wall, {tan_c:.1f} s CPU", flush=True)
    # two columns against central differences of the simulated residual (step 1e-2 in log E)
    norms = np.linalg.norm(J, axis=0)
    check = []
    for j in (int(np.argmax(norms)), int(np.argmin(norms))):
        e = np.zeros(k)
        e[j] = 1e-2
        fd = (residual(e) - residual(-e)) / 2e-2
        check.append({"patch": j, "column_norm": float(norms[j]),
                      "relative_error": float(np.linalg.norm(J[:, j] - fd) / max(np.linalg.norm(fd), 1e-300))})
        print(f"column {j}: |J| {norms[j]:.3g}, relative error against central differences "
              f"{check[-1]['relative_error']:.3g}", flush=True)
    said = []
    (mat, info), fit_w, fit_c = timed(lambda: field.fit_stiffness_field(
        sc, base, sc.damping, iterations=args.iterations, max_patches=args.patches,
        log=lambda m: (said.append(m), print(m, flush=True))))
    z = np.asarray(sc.mesh.vertices)[np.asarray(sc.mesh.tets)].mean(axis=1)[:, 2]
    logE = np.log(np.asarray(mat.youngs_modulus))
    contrast = float(logE[z > 0].mean() - logE[z < 0].mean())
    fd_iteration_w = (k + 1) * sim_w
    tangent_iteration_w = tan_w + sim_w * max(info["simulations"] - 1, 1) / max(info.get("iterations_done", 1), 1)
    out = {"benchmark": "field_scale", "tets": int(sc.mesh.num_tets), "vertices": int(sc.mesh.num_vertices),
           "recording_s": args.duration, "time_step_s": sc.time_step, "residual_rows": int(len(r0)),
           "patches": k, "simulation_s": sim_w, "simulation_cpu_s": sim_c,
           "tangent_pass_s": tan_w, "tangent_pass_cpu_s": tan_c,
           "ratio_tangent_pass_to_simulation": tan_w / sim_w,
           "ratio_tangent_pass_to_simulation_cpu": tan_c / sim_c,
           "fd_jacobian_simulations": k, "ratio_fd_jacobian_to_tangent_pass": k * sim_w / tan_w,
           "column_check": check,
           "fit_s": fit_w, "fit_cpu_s": fit_c, "fit_info": info,
           "fit_per_iteration_s": tangent_iteration_w, "fd_per_iteration_estimate_s": fd_iteration_w,
           "upper_minus_lower_log_stiffness": contrast, "truth_log_contrast": float(np.log(4.0)),
           "case_build_s": case_s, "load_avg_1min_start": load0, "load_avg_1min_end": os.getloadavg()[0],
           "cpus": os.cpu_count(), "commit": code_commit()}
    print(f"\n| quantity | value |\n|---|---|\n| simulation (reference) | {sim_w:.1f} s |\n"
          f"| tangent pass, {k} columns | {tan_w:.1f} s ({tan_w / sim_w:.1f} simulations) |\n"
          f"| finite-difference Jacobian | {k} simulations ({k * sim_w / tan_w:.0f}x the tangent pass) |\n"
          f"| tangent fit | {fit_w:.0f} s, {info.get('iterations_done')} iterations, {info['simulations']} simulations |\n"
          f"| train rms | {info['train_rms_pct_before']:.4g} -> {info['train_rms_pct']:.4g} % |\n"
          f"| upper - lower log E | {contrast:.2f} (truth {np.log(4.0):.2f}) |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
