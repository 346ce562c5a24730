"""Withheld-effect benchmark for `matlearn diagnose` (issue 5).

For every effect of the vocabulary a synthetic case whose truth has it (simulated on a finer mesh
than the model's, so a discretisation gap exists as with real data), a control case without any
effect and two cases combining two effects. Shapes (bar proportions, resolutions), magnitudes and
signs vary between cases; nothing in matlearn.diagnosis is told the effect or tuned to a case.

    python bench/diagnosis_suite.py [--work DIR] [--only NAME ...] [--fresh]

Writes bench/results/diagnosis_suite.json: {"cases": [{case, true_effects, verdict,
top1_correct, region_iou, gap_before_pct, gap_after_pct, wall_s, ...}], "totals": {...}}.
Per-case results are cached in the work folder, so an interrupted run resumes.

top1_correct: the verdict's first effect is a true effect, or a true effect is listed in its
`confounded_with` (density and stiffness scale cannot be told apart when every load is gravity
or a prescribed motion); for the control case: the verdict is []. gap_*_pct: held-out max error,
% of object size, before and after the verdict's effects were added.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from matlearn import _core, meshes
from matlearn.diagnosis import diagnose
from matlearn.materials import Damping, Material, make_model
from matlearn.synthetic import Motion, make_case

ROOT = Path(__file__).resolve().parent
RHO = 1000.0


def _bar(L, W, H, cells):
    return meshes.bar(L, W, H, cells)


class DamageCorrection:
    """History-dependent truth (Mullins-like damage): each element softens by
    d = min(dmax, k * max-so-far |s - 1|); the state persists across steps and recordings."""

    def __init__(self, mu, lam, k, dmax):
        self.mu, self.lam, self.k, self.dmax = mu, lam, k, dmax
        self.peak = None

    def __call__(self, Fh, Fhdot):
        Fh = np.asarray(Fh)
        e = Fh - 1.0
        if self.peak is None or len(self.peak) != len(Fh):
            self.peak = np.zeros(len(Fh))
        self.peak = np.maximum(self.peak, np.abs(e).max(axis=1))
        d = np.minimum(self.dmax, self.k * self.peak)[:, None]
        P = 2 * self.mu[:, None] * e + self.lam[:, None] * e.sum(axis=1, keepdims=True)
        J = np.zeros((len(Fh), 3, 3))
        J[:] = -(self.lam[:, None, None] * np.ones((3, 3)) + 2 * self.mu[:, None, None] * np.eye(3))
        return -d * P, d[:, :, None] * J, None, None


class SidePoly:
    """Truth one-sided nonlinearity of a shape unlike the diagnosis family: exponential
    stiffening/softening E * a * (exp(b d) - 1 - b d) / b on one side of s = 1."""

    def __init__(self, E, a, b, side):
        self.E, self.a, self.b, self.side = E, a, b, side

    def __call__(self, Fh, Fhdot):
        Fh = np.asarray(Fh)
        d = np.clip(self.side * (Fh - 1.0), 0, None)
        P = self.side * self.E * self.a * (np.exp(self.b * d) - 1 - self.b * d) / self.b
        dd = self.E * self.a * (np.exp(self.b * d) - 1)
        J = np.zeros(Fh.shape + (3,))
        J[:, np.arange(3), np.arange(3)] = dd
        return P, J, None, None


def case_specs():
    """name -> dict(true_effects, shape, truth edits). Magnitudes/signs vary on purpose."""
    return {
        "control": dict(effects=[], L=0.14, cells=(8, 3, 3)),
        "stiffness_scale": dict(effects=["stiffness_scale"], L=0.15, cells=(8, 3, 3), E=1.4),
        "poisson_ratio": dict(effects=["poisson_ratio"], L=0.13, W=0.04, H=0.035, cells=(8, 3, 3), nu=0.25),
        "tension_nonlinearity": dict(effects=["tension_nonlinearity"], L=0.15, cells=(8, 3, 3),
                                     side=(1.0, 3.0, 40.0)),
        "compression_nonlinearity": dict(effects=["compression_nonlinearity"], L=0.14,
                                         cells=(8, 3, 3), side=(-1.0, 3.0, 40.0)),
        "rayleigh_damping": dict(drive=True, effects=["rayleigh_damping"], L=0.15, W=0.032, cells=(8, 3, 3),
                                 damping=Damping(4.0, 0.004)),
        "strain_dependent_damping": dict(effects=["strain_dependent_damping"], L=0.14,
                                         cells=(8, 3, 3),
                                         damping=Damping(0.0, 0.002, [], [0.3, 40.0])),
        "heterogeneity": dict(drive=True, effects=["heterogeneity"], L=0.16, cells=(9, 3, 3),
                              region=(0.35, 0.65), region_scale=0.3),
        "density": dict(effects=["density"], L=0.14, W=0.04, H=0.03, cells=(8, 3, 3), rho=1.5),
        "support_compliance": dict(drive=True, effects=["support_compliance"], L=0.15, cells=(8, 3, 3),
                                   soft_layer=0.1),
        "history_dependence": dict(effects=["history_dependence"], L=0.15, cells=(8, 3, 3),
                                   damage=(8.0, 0.5)),
        "combined_stiffness_damping": dict(drive=True, effects=["stiffness_scale", "rayleigh_damping"],
                                           L=0.15, cells=(8, 3, 3), E=0.7,
                                           damping=Damping(3.0, 0.004)),
        "combined_heterogeneity_tension": dict(drive=True, effects=["heterogeneity", "tension_nonlinearity"],
                                               L=0.16, cells=(9, 3, 3), region=(0.0, 0.3),
                                               region_scale=2.5, side=(1.0, 2.0, 40.0)),
    }


def build_case(work: Path, name: str, spec: dict, seed: int, reuse: bool = True) -> tuple[Path, np.ndarray | None]:
    L, W, H = spec["L"], spec.get("W", 0.035), spec.get("H", 0.035)
    cells = spec["cells"]
    model_mesh = _bar(L, W, H, cells)
    truth_mesh = _bar(L, W, H, tuple(int(np.ceil(1.5 * c)) for c in cells))
    E0, nu0 = 6e5, 0.4
    m = truth_mesh.num_tets
    C = np.asarray(truth_mesh.vertices)[np.asarray(truth_mesh.tets)].mean(axis=1)
    E = np.full(m, E0 * spec.get("E", 1.0))
    region_model = None
    if "region" in spec:
        a, b = spec["region"]
        inside = (C[:, 0] >= a * L) & (C[:, 0] <= b * L)
        E[inside] *= spec["region_scale"]
        Cm = np.asarray(model_mesh.vertices)[np.asarray(model_mesh.tets)].mean(axis=1)
        region_model = np.flatnonzero((Cm[:, 0] >= a * L) & (Cm[:, 0] <= b * L))
    if "soft_layer" in spec:
        E[C[:, 0] < 0.08 * L] *= spec["soft_layer"]
    truth_mat = Material("corotated", E, spec.get("nu", nu0), RHO * spec.get("rho", 1.0))
    nominal_damping = Damping(0.0, 0.002)
    truth_damping = spec.get("damping", nominal_damping)
    correction = None
    mu, lam = truth_mat.lame(m)
    if "side" in spec:
        side, a, b = spec["side"]
        correction = _core.correction.PythonCorrection(SidePoly(E0, a, b, side))
    if "damage" in spec:
        k, dmax = spec["damage"]
        correction = _core.correction.PythonCorrection(DamageCorrection(mu, lam, k, dmax))
    tip = [[L - 0.2 * L, -1, -1], [1, 1, 1]]
    rng = np.random.default_rng(seed)
    f = 1.5 * (1 + 0.3 * rng.random()) * spec.get("load", 0.5)
    dur = 0.2
    if "damage" in spec:
        # growing drive cycles: damage accumulates during the recording
        kf = [[0.0, [0, 0, 0]], [0.03, [0, 0.004, 0]], [0.06, [0, 0, 0]], [0.09, [0, 0.012, 0]],
              [0.12, [0, 0, 0]], [0.15, [0, 0.004, 0]], [0.18, [0, 0, 0]]]
        motions = [Motion("drive", "train", dur, drive={"box": tip, "keyframes": kf}),
                   Motion("drive", "train", dur, drive={"box": tip, "keyframes": [[t, [0, 0, d[1]]] for t, d in kf]}),
                   Motion("drive", "test", dur, drive={"box": tip, "keyframes": [[0.0, [0, 0, 0]], [0.05, [0, -0.008, 0.004]], [0.1, [0, 0, 0]]]})]
    elif spec.get("drive"):
        # the tip is moved and brought back by a (robot) drive, then held: no static hold solve
        a = 0.06 * L * (1 + 0.3 * rng.random())
        kf = lambda d: [[0.0, [0, 0, 0]], [0.04, d], [0.08, [0, 0, 0]]]  # noqa: E731
        motions = [Motion("drive", "train", dur, drive={"box": tip, "keyframes": kf([0, -a, 0.4 * a])}),
                   Motion("drive", "train", dur, drive={"box": tip, "keyframes": kf([0, 0.3 * a, a])}),
                   Motion("drive", "test", dur, drive={"box": tip, "keyframes": kf([0.2 * a, 0.8 * a, -a])})]
    else:
        motions = [Motion("release", "train", dur, load={"box": tip, "force": [0, -f, 0.4 * f]}, load_steps=12),
                   Motion("release", "train", dur, twist={"box": tip, "torque": [0.03 * f, 0, 0]}, load_steps=12),
                   Motion("release", "test", dur, load={"box": tip, "force": [0.3 * f, 0.8 * f, -f]}, load_steps=12)]
    nominal = Material("corotated", E0, nu0, RHO)
    if reuse and (work / name / "scene.toml").exists():
        return work / name / "scene.toml", region_model
    # the truth's static hold solve is sensitive to its load increments: retry with others
    for steps in (12, 5, 20, 8):
        for m_ in motions:
            m_.load_steps = steps
        try:
            path = make_case(work, name, truth_mesh, truth_mat, truth_damping, model_mesh, nominal,
                             nominal_damping, [[-1, -1, -1], [1e-6, 1, 1]], motions,
                             marker_fraction=0.3, noise=2e-5, seed=seed, truth_correction=correction)
            return path, region_model
        except RuntimeError as err:
            print(f"{name}: truth hold failed with {steps} load steps ({err})", file=sys.stderr)
            if "damage" in spec:  # stateful truth: start from a fresh correction
                correction = _core.correction.PythonCorrection(DamageCorrection(mu, lam, *spec["damage"]))
    raise RuntimeError(f"{name}: the truth's static hold failed for every load-step count")


def _commit() -> str:
    import subprocess

    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                             text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "python/matlearn/diagnosis"],
                               cwd=ROOT.parent, capture_output=True, text=True).stdout.strip()
        return out + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def iou(a, b) -> float:
    a, b = set(map(int, a)), set(map(int, b))
    return len(a & b) / max(len(a | b), 1)


def score_case(name, spec, result, region_model, wall):
    verdict = result["verdict"]
    true = spec["effects"]
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
            "region_iou": region_iou, "gap_before_pct": before, "gap_after_pct": after,
            "wall_s": wall}


def totals(rows):
    eff = [r for r in rows if r["true_effects"]]
    ctrl = [r for r in rows if not r["true_effects"]]
    shrink = [1 - r["gap_after_pct"] / r["gap_before_pct"] for r in eff if r["gap_before_pct"]]
    ious = [r["region_iou"] for r in rows if r["region_iou"] is not None]
    return {
        "cases": len(rows),
        "top1_accuracy": float(np.mean([r["top1_correct"] for r in eff])) if eff else None,
        "control_clean": all(r["verdict"] == [] for r in ctrl),
        "failed_cases": [r["case"] for r in rows if r.get("error")],
        "mean_region_iou": float(np.mean(ious)) if ious else None,
        "median_gap_shrink": float(np.median(shrink)) if shrink else None,
        "total_wall_s": float(sum(r["wall_s"] for r in rows)),
        "max_wall_s": float(max(r["wall_s"] for r in rows)) if rows else None,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(ROOT / "work" / "diagnosis_suite"))
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--fresh", action="store_true", help="rebuild cases and rediagnose")
    ap.add_argument("--rediagnose", action="store_true", help="keep built cases, rediagnose")
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    specs = case_specs()
    names = args.only or list(specs)
    rows = []
    for i, name in enumerate(names):
        spec = specs[name]
        cache = work / name / "suite_row.json"
        if cache.exists() and not (args.fresh or args.rediagnose):
            rows.append(json.loads(cache.read_text()))
            print(f"{name}: cached", file=sys.stderr)
            continue
        print(f"== {name} ({i + 1}/{len(names)}): building truth", file=sys.stderr, flush=True)
        t0 = time.time()
        try:
            path, region_model = build_case(work, name, spec, seed=100 + i, reuse=not args.fresh)
            t0 = time.time()
            result = diagnose(path, work / name / "diagnosis", seed=0,
                              report=(name in ("heterogeneity",)))
            row = score_case(name, spec, result, region_model, time.time() - t0)
        except (RuntimeError, ValueError) as err:  # a failed case is reported, not hidden
            row = {"case": name, "true_effects": spec["effects"], "verdict": None,
                   "top1_correct": False, "region_iou": None, "gap_before_pct": None,
                   "gap_after_pct": None, "wall_s": time.time() - t0, "error": str(err)}
        row["commit"] = _commit()
        cache.write_text(json.dumps(row))
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    out = {"cases": rows, "totals": totals(rows)}
    res = ROOT / "results" / "diagnosis_suite.json"
    res.parent.mkdir(exist_ok=True)
    if not args.only:
        res.write_text(json.dumps(out, indent=1))
    print(f"{'case':32s} {'true':40s} {'verdict':40s} top1 iou   before after  wall")
    for r in rows:
        if r.get("error"):
            print(f"{r['case']:32s} FAILED: {r['error']}")
            continue
        iou_s = "-" if r["region_iou"] is None else f"{r['region_iou']:.2f}"
        print(f"{r['case']:32s} {','.join(r['true_effects']):40s} {','.join(r['verdict']):40s} "
              f"{'yes' if r['top1_correct'] else 'no ':4s} {iou_s:5s} {r['gap_before_pct']:6.2f} "
              f"{r['gap_after_pct']:6.2f} {r['wall_s']:5.0f}")
    print(json.dumps(out["totals"], indent=1))


if __name__ == "__main__":
    main()
