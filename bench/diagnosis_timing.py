"""Speed of `matlearn diagnose` at the issue's scale: one diagnosis of a ~3k-tet model with two
recordings (one train, one larger test; the truth, 1.25x finer to keep its build short, has a softer
material).
Run through `python bench/diagnosis_suite.py --timing`; the wall time goes to
bench/results/diagnosis_suite.json as totals.timing_3k (s), with totals.timing_3k_info."""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from matlearn.diagnosis import diagnose

SPEC = {"effects": ["stiffness_scale"], "truth": {"stiffness_scale": 0.75},
        "shape": {"kind": "bar", "L": 0.2, "W": 0.05, "H": 0.05, "cells": (20, 5, 5),
                  "truth_factor": 1.25},
        "motions": [("load", "train", 0.04, 0.3), ("load", "test", 0.06, 2.0)],
        "E0": 1.5e6, "nu0": 0.4, "rho0": 1000.0, "duration": 0.2}


def run_timing(work: Path, results: Path, fresh: bool = False) -> int:
    from diagnosis_suite import build_case, score_case

    work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    path, region = build_case(work, "timing_3k", SPEC, seed=5, reuse=not fresh)
    build = time.time() - t0
    t0 = time.time()
    load_start = os.getloadavg()[0]
    milestones = {}

    def progress(line):  # "[diagnose   12.3s] where: ..." -> stage milestones (s)
        print(line, file=sys.stderr, flush=True)
        stage = line.split("] ", 1)[-1].split(":")[0].split(" (")[0]
        for key in ("where", "discretisation", "sensitivities done", "region boundary",
                    "verdict", "wrote"):
            if stage.startswith(key) and not stage.startswith("discretisation credit"):
                milestones[key] = round(time.time() - t0, 1)  # the stage's last message

    result = diagnose(path, work / "timing_3k" / "diagnosis", seed=0, report=True, progress=progress)
    wall = time.time() - t0
    row = score_case("timing_3k", SPEC, result, region, wall)
    from matlearn.scene import load_scene

    scene = load_scene(path)
    info = {"model_tets": scene.mesh.num_tets, "recordings": len(scene.recordings),
            "steps_per_recording": int(round(SPEC["duration"] / scene.time_step)),
            "simulations": result["simulations"], "verdict": result["verdict"],
            "build_truth_s": build, "load_avg_1min": os.getloadavg()[0],
            "load_avg_1min_at_start": load_start, "cores": os.cpu_count(),
            "milestones_s": milestones, "commit": _commit()}
    print(json.dumps({**row, **info}, indent=1))
    out = json.loads(results.read_text()) if results.exists() else {"cases": [], "totals": {}}
    out.setdefault("totals", {})["timing_3k"] = wall
    out["totals"]["timing_3k_info"] = info
    results.write_text(json.dumps(out, indent=1))
    print(f"timing_3k: {wall:.0f} s for one diagnosis ({info['model_tets']} tets, "
          f"{info['recordings']} recordings, {info['simulations']} simulations)", file=sys.stderr)
    return 0


def _commit():
    from diagnosis_suite import _commit as c

    return c()
