"""Benchmark: the learning's independent simulations on the cores (matlearn.parallel).

For learning-table cases (matlearn.cases), in one process and the same run:
* the released start of every recording (`replay.initial_state(start="released")`: its
  candidate holds and its refinement's Jacobian columns side by side),
* `score` of the train and test recordings (the loop's forward checks and every held-out
  score run the recordings side by side),
* the Wang-2015 baseline fit (`fit_parameters`, its finite-difference columns side by side),
* the stress-scale check of the nominal model (`identify.stress_scale_check`, its factors side
  by side),
each timed with MATLEARN_THREADS=1 (the reference) and with the machine's threads, the results
compared bitwise; and the RBF fit's tangent-penalty Gram matrix (`FitSystem._gradient_gram`, one
BLAS product) against the einsum it replaced (the einsum's time includes the kernel gradients
that the method computes too; same inputs, relative difference reported).
Writes bench/results/learning_parallel.json and prints a table of the ratios.

Usage: python bench/learning_parallel.py [--cases dragon,layered_bar,...] [--work DIR] [--out FILE]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from matlearn import cases, parallel
from matlearn.embedding import embed_points
from matlearn.learning import fit as fit_mod
from matlearn.learning.baseline import fit_parameters
from matlearn.learning.identify import stress_scale_check, with_stress_factor
from matlearn.replay import initial_state, score
from matlearn.scene import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import code_commit  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "learning_parallel.json"
DEFAULT = "dragon,bar_damping_1,layered_bar,turtle"


def timed(fn, threads: str, repeat: int = 1):
    """(result, best wall s over `repeat`) of fn() with MATLEARN_THREADS=threads."""
    os.environ["MATLEARN_THREADS"] = threads
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def same(a, b) -> bool:
    """Bitwise equal nested results (dicts, lists, arrays, floats, specs)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, (np.ndarray, float, int)):
        return np.array_equal(np.asarray(a), np.asarray(b))
    return a == b


def gram_check() -> dict:
    """The tangent-penalty Gram matrix at 4000 stretch samples and 24 centres x 6: the fit's own
    `FitSystem._gradient_gram` (one BLAS product) against the einsum it replaced."""
    rng = np.random.default_rng(0)
    S = 1.0 + 0.05 * rng.standard_normal((4000, 3))
    C = 1.0 + 0.05 * rng.standard_normal((144, 3))
    eps = 0.02
    system = SimpleNamespace(centers=C, epsilon=eps, box=fit_mod.centers_box(C, eps))  # what it reads
    t = time.perf_counter()
    G = fit_mod.kernel_gradients(S, C, eps, system.box)
    ref = np.einsum("ikb,ilb->kl", G, G) / len(S)
    t_ref = time.perf_counter() - t
    t = time.perf_counter()
    new = fit_mod.FitSystem._gradient_gram(system, S)
    t_new = time.perf_counter() - t
    return {"einsum_s": t_ref, "blas_s": t_new, "ratio": t_ref / t_new,
            "max_rel_diff": float(np.abs(new - ref).max() / np.abs(ref).max())}


def run_case(name: str, work: Path, cores: str) -> dict:
    spec = getattr(cases, name)()
    scene = load_scene(cases.build(spec, work / "cases"))
    row = {"case": name, "tets": scene.mesh.num_tets,
           "train_recordings": len(scene.recordings_with_role("train")),
           "test_recordings": len(scene.recordings_with_role("test"))}
    recs = scene.recordings_with_role("train") + scene.recordings_with_role("test")
    tasks = {
        "released_starts": lambda: [initial_state(scene, scene.model(), r, embed_points(scene.mesh, r.marker_rest),
                                                  start="released")[0] for r in recs],
        "score_train": lambda: score(scene, scene.model(), "train"),
        "score_test": lambda: score(scene, scene.model(), "test"),
        "baseline_fit_10": lambda: fit_parameters(scene, max_evaluations=10),
        "stress_scale_check": lambda: stress_scale_check(
            scene, lambda f: scene.model(material=with_stress_factor(scene.material, f))),
    }
    for key, fn in tasks.items():
        one, t1 = timed(fn, "1")
        many, tn = timed(fn, cores)
        row[key] = {"one_thread_s": t1, f"{cores}_threads_s": tn, "speedup": t1 / tn,
                    "bitwise_equal": same(one, many)}
        print(f"  {name:14s} {key:20s} {t1:8.2f} s -> {tn:8.2f} s  x{t1 / tn:4.2f}  equal: {row[key]['bitwise_equal']}",
              flush=True)
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default=DEFAULT)
    ap.add_argument("--work", default="/tmp/matlearn_learning_parallel")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    saved = os.environ.get("MATLEARN_THREADS")
    os.environ.pop("MATLEARN_THREADS", None)
    cores = str(parallel.threads())
    work = Path(args.work)
    rows = [run_case(n, work, cores) for n in args.cases.split(",")]
    gram = gram_check()
    print(f"  gram (4000 x 144 x 3): einsum {gram['einsum_s']:.3f} s, BLAS {gram['blas_s']:.4f} s, "
          f"x{gram['ratio']:.1f}, max rel diff {gram['max_rel_diff']:.1e}")
    if saved is not None:
        os.environ["MATLEARN_THREADS"] = saved
    out = {"benchmark": "learning_parallel", "code_commit": code_commit(("python/matlearn", "cpp")),
           "threads": int(cores), "cores": os.cpu_count(), "cases": rows, "gram": gram,
           "notes": "speedup = one-thread wall / threaded wall, both in this run; bitwise_equal: "
                    "the threaded result equals the one-thread result exactly"}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print("wrote", args.out)


if __name__ == "__main__":
    main()
