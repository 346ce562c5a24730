"""How far each independent-suite "reality" mesh is from the continuum, against the model's mesh.

The independent suite (bench/diagnosis_independent.py) simulates its truth on a finer mesh of the
same surface, assuming a finer mesh is closer to the continuum than the model's. For each case this
measures the first angular frequency (rad/s) of the nominal material, clamped as in the case, on the
model's mesh, the model's once-refined mesh (matlearn.meshes.refine_tets), the truth's mesh and the
truth's once-refined mesh. (w_truth / w_model)^2 is the stiffness factor the truth's mesh alone asks of
the model (a control's recordings ask for it); (w_truth / w_truth_refined)^2 > 1 says the truth's mesh
is itself far from converged, stiffer than its own refinement. No diagnosis is run.

    python bench/independent_mesh_check.py [--seeds 11 12 13 14] [--shuffled 16] [--out FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
import numpy as np  # noqa: E402

import diagnosis_independent as di  # noqa: E402
from matlearn import meshes  # noqa: E402
from matlearn.materials import Material  # noqa: E402
from provenance import code_commit  # noqa: E402

ROOT = Path(__file__).resolve().parent


def first_frequency(mesh, mat, clamp) -> float:
    fixed = di.in_box(np.asarray(mesh.vertices), clamp)
    return di.linear_props(mesh, mat, fixed, fixed[:1], [0.0, 0.0, -9.81])[0]


def check_case(seed: int, shape_kind: str) -> dict:
    """Rebuild the case's meshes exactly as build_case does (its rng draws the shape first)."""
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        shape = di.make_shape(shape_kind, rng, Path(tmp))
    mat = Material("corotated", 1e6, 0.35, 1000.0)  # frequencies scale with sqrt(E / rho) alike
    out = {"shape": shape_kind, "model_tets": shape["model"].num_tets, "truth_tets": shape["truth"].num_tets}
    for name, mesh in (("model", shape["model"]), ("truth", shape["truth"])):
        V, T = meshes.refine_tets(np.asarray(mesh.vertices), np.asarray(mesh.tets))
        out[f"w_{name}"] = first_frequency(mesh, mat, shape["clamp"])
        out[f"w_{name}_refined"] = first_frequency(meshes.TetMesh(V, T), mat, shape["clamp"])
    out["truth_mesh_stiffness"] = (out["w_truth"] / out["w_model"]) ** 2
    out["refined_mesh_stiffness"] = (out["w_model_refined"] / out["w_model"]) ** 2
    out["truth_over_its_refinement"] = (out["w_truth"] / out["w_truth_refined"]) ** 2
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[11, 12, 13, 14])
    ap.add_argument("--shuffled", type=int, nargs="*", default=[16])
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "independent_mesh_check.json")
    args = ap.parse_args(argv)
    rows = []
    print(f"{'seed':>9s} {'case':14s} {'shape':10s} {'tets m/t':>10s} {'truth/model':>11s} "
          f"{'refined/model':>13s} {'truth/its refined':>17s}")
    for seed, shuffled in [(s, False) for s in args.seeds] + [(s, True) for s in args.shuffled]:
        shapes = di.shuffled_shapes(seed) if shuffled else [c[2] for c in di.CASES]
        for i, ((name, _, _), kind) in enumerate(zip(di.CASES, shapes)):
            r = check_case(1000 * seed + i, kind)
            r.update(seed=seed, shuffled=shuffled, case=name)
            rows.append(r)
            print(f"{seed:>6d}{'s' if shuffled else ' ':3s} {name:14s} {kind:10s} {r['model_tets']:>4d}/{r['truth_tets']:<5d} "
                  f"{r['truth_mesh_stiffness']:11.3f} {r['refined_mesh_stiffness']:13.3f} "
                  f"{r['truth_over_its_refinement']:17.3f}", flush=True)
    stiffer = [r for r in rows if r["truth_mesh_stiffness"] > 1.0]
    res = {"notes": {"commit": code_commit(), "what": __doc__.split("\n\n")[1].replace("\n", " "),
                     "truth_stiffer_than_model": [f"{r['seed']}{'s' if r['shuffled'] else ''}/{r['case']} "
                                                  f"({r['shape']}, x{r['truth_mesh_stiffness']:.2f})" for r in stiffer]},
           "cases": rows}
    args.out.write_text(json.dumps(res, indent=1))
    print(f"{len(stiffer)} of {len(rows)} truths' meshes are stiffer than the model's; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
