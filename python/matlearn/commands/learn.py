"""`matlearn learn SCENE --out RUN`: learn an elastic + damping correction from the scene's train
recordings (sparse reduced space-time optimisation, RBF stress fitting), score it on the test
recordings, distil it into an MLP, and write RUN/model.npz + model.json (for `matlearn simulate
--model RUN`), metrics.json, convergence.png and error_histograms.png.

Recordings may be markers or point clouds (cloud_points/cloud_offsets/cloud_sigma): cloud-only
recordings are tracked first with the physics-based tracker (progress shown, cached in
RUN/tracked/ so --resume does not track again) and learned through their tracked markers.

`--start field` learns from the fitted parameters with a per-element Young's modulus fitted on
top (learning/field.py: heterogeneous objects). `--start best` learns from the nominal, the fitted
parameters and the field (RUN/start_nominal, RUN/start_baseline, RUN/start_field, each with its
own metrics.json and checkpoints) and keeps the model whose learned train error is lowest
(RUN/best_start.json). `--laws all` lets these starts fit every standard law (co-rotated,
neo-Hookean, St. Venant-Kirchhoff) and start from the one the train recordings support best."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def run(args) -> int:
    from ..learning import LearnOptions, save_model
    from ..learning.fit import EXTRAPOLATION_WEIGHTS
    from ..learning.plots import plot_convergence, plot_error_histograms
    from ..scene import load_scene

    scene = load_scene(args.scene)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; learn writes a run folder (model, metrics, plots)")
    if out.exists() and any(out.iterdir()) and not args.resume and not args.force:
        raise ValueError(f"{out} exists and is not empty; use --resume to continue it or --force")
    if args.resume and not (out.is_dir() and any(out.iterdir())):
        print(f"learn: nothing to resume in {out} (no earlier run there); starting a new run",
              file=sys.stderr)
    opts = LearnOptions(iterations=args.iterations, lam=args.lam, modes=args.modes,
                        centers=args.centers, seed=args.seed,
                        refresh_correspondences=args.refresh_correspondences,
                        extrapolation=EXTRAPOLATION_WEIGHTS, tangent_damping=args.tangent_damping,
                        extend=tuple(args.extend))
    t0 = time.time()
    log = (lambda *a: print(*a, file=sys.stderr, flush=True)) if not args.quiet else None
    from ..learning.start import learn_from, model_meta

    # best: three starts, the lowest learned train error kept (RUN/start_<name>)
    scene, start, res, run_dir = learn_from(scene, args.start, out, opts, resume=args.resume, log=log,
                                            laws=_laws(args.laws))
    params = res["params"]
    summary = {"scene": str(Path(args.scene).resolve()), "best_iteration": res["best_iteration"],
               "lambda": res["lambda"],
               "start": start, "nominal": res["nominal"], "final": res["final"], "wall_s": None}
    mlp = None
    # the model the loop started from: the scene's nominal one, or a fitted start's material
    kept = start.get("chosen", args.start) if args.start == "best" else args.start
    first = "nominal" if kept == "nominal" else f"{kept} start"
    summary["nominal_model"] = first  # what "nominal" (the loop's iteration 0) was scored with
    if params is None:
        print(f"no learned correction improves on the {first} model; writing a zero correction",
              file=sys.stderr)
        from ..learning.start import zero_params

        params = zero_params()
    elif not args.no_distill:
        from ..learning.distill import compare, simulation_samples, train_mlp
        from ..learning.io import mlp_correction

        if log:
            log("distilling into an MLP 6-6-6-4 (stress + damping change) ...")
        tscene = res["scene"]  # cloud recordings replaced by their tracked markers
        X, Y = simulation_samples(tscene, params.correction(), tscene.recordings_with_role("train"),
                                  seed=args.seed)
        mlp, tinfo = train_mlp(X, Y, seed=args.seed)
        summary["distill"] = {**tinfo, **compare(params.correction(), mlp_correction(mlp), X, Y)}
    save_model(out, params, mlp, meta={"scene": summary["scene"], "best_iteration": res["best_iteration"],
                                       "start": args.start, **model_meta(start)})
    # does the stress level follow from the recordings? (a slowly driven object's does not;
    # learn_from has checked the kept model)
    from ..learning.io import add_meta

    check = start["stress_scale"]
    summary["stress_scale"] = check
    add_meta(out, stress_scale_determined=check["determined"], stress_scale_message=check["message"])
    if not check["determined"] or check["best_factor"] != 1.0:  # free, or the model off the data's scale
        print(f"warning: {check['message']}", file=sys.stderr)
    elif log:
        log(check["message"])
    plot_convergence(res["metrics"], out / "convergence.png")
    import numpy as np

    with np.load(run_dir / "error_samples.npz") as z:
        plot_error_histograms({k: z[k] for k in z.files}, out / "error_histograms.png")
    # this command's time (after --resume, the resumed part; metrics.json has every iteration's)
    summary["wall_s"] = time.time() - t0
    summary["resumed"] = bool(args.resume)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    nom, fin = res["nominal"], res["final"]
    role = "test" if nom.get("test") else "train"
    print(f"{role} max error: {first} {nom[role]['max_error_pct']:.3f}% -> learned "
          f"{fin[role]['max_error_pct']:.3f}% (iteration {res['best_iteration']}); model in {out}")
    return 0


def _laws(text: str):
    """--laws: "own" (None: the scene's law), "all" (start.STANDARD_LAWS) or a comma list."""
    from ..learning.start import STANDARD_LAWS

    if text == "own":
        return None
    laws = STANDARD_LAWS if text == "all" else tuple(w.strip() for w in text.split(",") if w.strip())
    bad = [w for w in laws if w not in STANDARD_LAWS]
    if bad or not laws:
        raise ValueError(f"--laws: unknown law(s) {bad or text!r}; expected 'own', 'all' or a comma list "
                         f"of {', '.join(STANDARD_LAWS)}")
    return laws


def register(subparsers) -> None:
    p = subparsers.add_parser("learn", help="learn an elastic + damping correction from recordings",
                              description=__doc__)
    p.add_argument("scene", help="scene.toml with train (and test) recordings")
    p.add_argument("--out", required=True, help="run folder for the model, metrics and plots")
    p.add_argument("--iterations", type=int, default=8, help="max outer iterations (default 8)")
    p.add_argument("--resume", action="store_true", help="continue a killed run in --out")
    p.add_argument("--force", action="store_true", help="write into a non-empty --out")
    p.add_argument("--lambda", dest="lam", type=float, default=None,
                   help="dimensionless observation weight (default: 1 for markers; for point clouds "
                        "min(1, a_rms h^2 / sigma_obs) from the scan noise, see docs/point_clouds.md)")
    p.add_argument("--modes", type=int, default=20, help="POD modes r (default 20)")
    p.add_argument("--centers", type=int, default=24, help="RBF centres (default 24)")
    p.add_argument("--start", choices=("nominal", "baseline", "field", "best"), default="nominal",
                   help="start from the scene's nominal parameters, or from E, nu, alpha_K fitted to the "
                        "train recordings first (alpha_M held: the Wang-2015 baseline less the term the "
                        "learner cannot undo; the learned model then never fits the train recordings "
                        "worse than that fit), or field: that fit plus a per-element Young's modulus "
                        "fitted on top (a heterogeneous object: layers, inclusions), or best: learn "
                        "from all three (RUN/start_nominal, RUN/start_baseline, RUN/start_field) and "
                        "keep the lowest learned train error (about three times the time)")
    p.add_argument("--laws", default="own",
                   help="the laws whose E, nu, alpha_K the baseline, field and best starts fit, the one with "
                        "the lowest train rms kept and corrected: own (the scene's law, default), all "
                        "(co-rotated, neo-Hookean, St. Venant-Kirchhoff; bench/learning_table.py) or a comma list")
    p.add_argument("--no-distill", action="store_true", help="skip the MLP distillation")
    p.add_argument("--tangent-damping", action="store_true",
                   help="the stiffness-proportional Rayleigh damping acts on the corrected tangent "
                        "(alpha_K K(nominal + correction)) instead of the nominal one; see docs/results.md, "
                        "Learning")
    p.add_argument("--extend", type=float, nargs="*", default=[], metavar="T",
                   help="an update that lowers the train error is also tried at these multiples of "
                        "itself (e.g. 2 4), each kept while it lowers the train error further: fewer "
                        "iterations, but the held-out error can rise (docs/results.md, Learning); default none")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed (k-means centres, MLP training); the same seed gives the same model")
    p.add_argument("--refresh-correspondences", type=int, default=0, metavar="N",
                   help="point clouds: rounds of re-estimating the correspondences at the space-time "
                        "trajectory and solving again (default 0: the tracker's)")
    p.add_argument("--quiet", action="store_true", help="no progress output (the final summary line only)")
    p.set_defaults(func=run)
