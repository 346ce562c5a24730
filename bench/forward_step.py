"""Benchmark of matlearn's implicit (backward Euler) step on clamped bars of about 1k, 10k and
50k tets, co-rotated and neo-Hookean, against in the same run:

* one CHOLMOD factorisation + solve of the same system matrix (timed inside the step, around
  the CHOLMOD calls only): `factor_solve_s`, per Newton iteration;
* a vectorised numpy/scipy implementation of the same step (bench/numpy_step.py, scipy's
  `spsolve`): `numpy_step_s`; its result is checked against ours;
* pbatoolkit (bench/peer_step.py, neo-Hookean only, if installed): `peer_step_s`.

`step_s` is one whole Newton time step (median of several; reuse_factorization off),
`newton_iteration_s` = step_s / Newton iterations (one element evaluation + assembly +
factorisation + solve, with all per-step overhead charged to it). `reuse_step_s` is the mean
step of the default integrator (the last factorisation reused while it contracts, chord
iterations), over the same steps, with its factorisations per step and its distance from the
Newton trajectory (relative to the motion). Prints a table and writes bench/results/forward_step.json.

    python bench/forward_step.py [--sizes 1000 10000 50000] [--steps 5]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from numpy_step import NumpyStepper  # noqa: E402
from peer_step import make_peer  # noqa: E402

from matlearn import _core, materials, meshes  # noqa: E402

E, NU, RHO = 1e5, 0.4, 1000.0
ALPHA_M, ALPHA_K = 0.5, 0.01
H = 1e-3
G = np.array([0.0, 0.0, -9.81])


def timed(fn):
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def bench_case(material: str, target_tets: int, steps: int, ref_steps: int, peer_max_tets: int):
    mesh = meshes.bar_with_tets(0.2, 0.04, 0.04, target_tets)
    mat = materials.Material(material, E, NU, RHO)
    model = materials.make_model(mesh, mat, materials.Damping(ALPHA_M, ALPHA_K))
    fixed = np.where(mesh.vertices[:, 0] < 1e-9)[0]
    # Newton (a factorisation per iteration): the per-iteration metrics against CHOLMOD.
    integ = _core.time.Integrator(model, fixed, H, G, reuse_factorization=False, extrapolate=False)
    f = np.zeros((mesh.num_vertices, 3))
    for _ in range(3):  # warm up: the bar is falling and bending, Newton does real work
        integ.step(f)
    x0, v0 = integ.x.copy(), integ.v.copy()
    step_s, iters, fs = [], [], []
    for _ in range(steps):
        step_s.append(timed(lambda: integ.step(f)))
        t = integ.last_timings
        iters.append(t["iterations"])
        fs.append((t["factorize_s"] + t["solve_s"]) / t["iterations"])
    step = float(np.median(step_s))
    n_iter = float(np.mean(iters))
    factor_solve = float(np.median(fs))
    # The default step (reused factorisations, extrapolated start) over the same steps: mean
    # time (the occasional refactorisation is part of the cost) and distance from Newton.
    fast = _core.time.Integrator(model, fixed, H, G)
    for _ in range(3):
        fast.step(f)
    fast_s, fast_it, fast_fac = [], [], []
    for _ in range(steps):
        fast_s.append(timed(lambda: fast.step(f)))
        fast_it.append(fast.last_timings["iterations"])
        fast_fac.append(fast.last_timings["factorizations"])
    fast_step = float(np.mean(fast_s))
    fast_diff = float(np.abs(fast.x - integ.x).max())
    fast_motion = float(np.abs(integ.x - mesh.vertices).max())

    # The numpy reference takes the same step from the same state; compare the result.
    mu, lam = mat.lame(mesh.num_tets)
    ref = NumpyStepper(mesh.vertices, mesh.tets, material, mu, lam, RHO, ALPHA_M, ALPHA_K, fixed,
                       H, G)
    check = _core.time.Integrator(model, fixed, H, G, reuse_factorization=False, extrapolate=False)
    check.set_state(x0, v0)
    check.step(f)
    ref_s = []
    for _ in range(ref_steps):
        ref.x, ref.v = x0.copy(), v0.copy()
        ref_s.append(timed(lambda: ref.step(f)))
    numpy_step = float(np.median(ref_s))
    motion = float(np.abs(check.x - x0).max())
    numpy_diff = float(np.abs(ref.x - check.x).max())

    peer_step = None
    if material == "neo_hookean" and mesh.num_tets <= peer_max_tets:
        peer = make_peer(mesh.vertices, mesh.tets, mu, lam, np.repeat(model.vertex_mass, 3),
                         ALPHA_M, ALPHA_K, fixed, H, G)
        if peer is not None:
            peer.x, peer.v = x0.copy(), v0.copy()
            peer.step(f)  # analysis + first factorisation outside the timing, as for ours
            peer.x, peer.v = x0.copy(), v0.copy()
            peer_step = timed(lambda: peer.step(f))
    return {
        "material": material,
        "tets": int(mesh.num_tets),
        "vertices": int(mesh.num_vertices),
        "newton_iterations": n_iter,
        "step_s": step,
        "newton_iteration_s": step / n_iter,
        "factor_solve_s": factor_solve,
        "numpy_step_s": numpy_step,
        "peer_step_s": peer_step,
        "iteration_over_factor_solve": step / n_iter / factor_solve,
        "numpy_over_step": numpy_step / step,
        "peer_over_step": None if peer_step is None else peer_step / step,
        "numpy_max_position_difference_m": numpy_diff,
        "step_max_displacement_m": motion,
        "numpy_steps_timed": ref_steps,
        "reuse_step_s": fast_step,
        "reuse_iterations": float(np.mean(fast_it)),
        "reuse_factorizations_per_step": float(np.mean(fast_fac)),
        "newton_over_reuse_step": step / fast_step,
        "reuse_vs_newton_max_position_difference_m": fast_diff,
        "reuse_vs_newton_relative_difference": fast_diff / max(fast_motion, 1e-300),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    ap.add_argument("--materials", nargs="+", default=["corotated", "neo_hookean"])
    ap.add_argument("--steps", type=int, default=20, help="timed steps of ours per case (each mode)")
    ap.add_argument("--out", default=str(HERE / "results" / "forward_step.json"))
    ap.add_argument("--peer-max-tets", type=int, default=60000,
                    help="skip the pbatoolkit peer above this size (its simplicial LDL^T is slow)")
    args = ap.parse_args(argv)
    rows = []

    def write():
        out = {
            "benchmark": "forward_step",
            "machine": platform.machine(),
            "cpu_count": os.cpu_count(),
            "load_average_at_end": list(os.getloadavg()),
            "time_step_s": H,
            "material_parameters": {"E": E, "nu": NU, "rho": RHO, "alpha_M": ALPHA_M, "alpha_K": ALPHA_K},
            "targets": {"iteration_over_factor_solve_max": 1.3, "numpy_over_step_min_10k": 10,
                        "numpy_over_step_min_50k": 30},
            "rows": rows,
        }
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    hdr = (f"{'material':<12}{'tets':>7}{'iters':>6}{'step_s':>9}{'iter_s':>9}{'fact+sol':>9}"
           f"{'numpy_s':>9}{'peer_s':>8}{'it/fs':>7}{'np/step':>8}{'reuse_s':>9}{'fac/st':>7}{'x fast':>7}")
    print(hdr)
    for n in args.sizes:
        for m in args.materials:
            r = bench_case(m, n, args.steps, 1 if n > 20000 else 3, args.peer_max_tets)
            rows.append(r)
            peer = "-" if r["peer_step_s"] is None else f"{r['peer_step_s']:.3f}"
            print(f"{m:<12}{r['tets']:>7}{r['newton_iterations']:>6.1f}{r['step_s']:>9.4f}"
                  f"{r['newton_iteration_s']:>9.4f}{r['factor_solve_s']:>9.4f}"
                  f"{r['numpy_step_s']:>9.3f}{peer:>8}{r['iteration_over_factor_solve']:>7.2f}"
                  f"{r['numpy_over_step']:>8.1f}{r['reuse_step_s']:>9.4f}"
                  f"{r['reuse_factorizations_per_step']:>7.2f}{r['newton_over_reuse_step']:>7.1f}", flush=True)
            if r["reuse_vs_newton_relative_difference"] > 1e-6:
                print(f"  warning: reused-factor steps differ from Newton by "
                      f"{r['reuse_vs_newton_relative_difference']:.2e} of the motion")
            if r["numpy_max_position_difference_m"] > 1e-6 * max(r["step_max_displacement_m"], 1e-9) + 1e-12:
                print(f"  warning: numpy reference differs by {r['numpy_max_position_difference_m']:.2e} m")
            write()  # after every row, so an interrupted run keeps what it measured
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
