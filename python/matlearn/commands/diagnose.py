"""`matlearn diagnose SCENE --out DIR`: what is the nominal model missing?"""
from __future__ import annotations


def register(subparsers):
    p = subparsers.add_parser(
        "diagnose",
        help="diagnose the sim-to-real gap of a scene's nominal model",
        description="Learn from the scene's train recordings where the nominal model is wrong, "
        "which unmodelled effect explains it and how far the held-out (test) gap shrinks once "
        "it is added. Writes DIR/diagnosis.json, DIR/report.html and DIR/residual_map.vtu.",
    )
    p.add_argument("scene", help="scene.toml")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed (k-means regions and patches); the same seed gives the same result")
    p.add_argument("--no-report", action="store_true", help="skip report.html and .vtu")
    p.add_argument("--residual", choices=("constrained", "spacetime"), default="constrained",
                   help="source of the control forces mapped in 'where' (spacetime: the learning "
                   "step's space-time optimisation, sharper, ~5x slower)")
    p.add_argument("--resume", action="store_true",
                   help="continue a killed diagnosis into the same --out: the simulations it finished "
                   "(kept in OUT/.diagnose_cache while it runs) are not run again")
    p.add_argument("--force", action="store_true",
                   help="overwrite an earlier diagnosis in --out (or start an interrupted one afresh)")
    p.add_argument("--follow-damping", action="store_true",
                   help="experimental: the mesh's discretisation error removed from the data follows "
                   "each candidate's Rayleigh damping (finds strong damping on coarse meshes, also "
                   "claims damping more often where there is none; docs/diagnosis_design.md)")
    p.set_defaults(func=_run)


def check_out(out, resume: bool, force: bool) -> None:
    """Refuse an --out that holds a finished or an interrupted diagnosis unless told what to do
    with it (nothing a user produced is overwritten silently)."""
    from pathlib import Path

    from ..diagnosis.simcache import FOLDER

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; diagnose writes a folder (diagnosis.json, report.html, ...)")
    if force or resume:
        return
    if (out / FOLDER).exists():
        raise ValueError(f"{out} holds an interrupted diagnosis ({FOLDER}); use --resume to continue it "
                         "or --force to start afresh")
    if (out / "diagnosis.json").exists():
        raise ValueError(f"{out} holds an earlier diagnosis (diagnosis.json); use --force to overwrite it "
                         "or choose another --out")


def _run(args):
    from ..diagnosis import diagnose

    check_out(args.out, args.resume, args.force)
    r = diagnose(args.scene, args.out, seed=args.seed, report=not args.no_report,
                 residual_source=args.residual, follow_damping=args.follow_damping or None,
                 resume=args.resume)
    print(f"verdict: {', '.join(r['verdict']) or '[] (within noise and discretisation)'}")
    d, gb = r.get("discretisation") or {}, r["gap_before"]
    from ..diagnosis.report import gap_label, mesh_advice

    parts = [f"{gap_label(bool(r.get('held_out')))} {gb['max_error_pct']:.2f} %"]
    if d.get("gap_with_offset"):
        parts.append(f"with the mesh's stiffness factor E x {d['stiffness_factor']:.3g} alone (no effect) "
                     f"{d['gap_with_offset']['max_error_pct']:.2f} %")
    if d.get("gap_refined_mesh"):
        parts.append(f"on the once-refined mesh {d['gap_refined_mesh']['max_error_pct']:.2f} %")
    print("; ".join(parts))
    advice = mesh_advice(r)
    if advice:
        print(f"{advice} (report.html, Mesh)")
    dec = r.get("decay") or {}
    if dec.get("ratio") is not None:
        print(f"decay: x{dec['ratio']:.2f} the nominal damping law's at the recorded frequencies"
              + (f": damping {dec['change']} (alpha_M {dec['alpha_mass']:.4g} 1/s, alpha_K {dec['alpha_stiffness']:.4g} s)"
                 if dec["change"] else " (no change concluded)"))
    hint = learning_hint(r, args.scene)
    if hint:
        print(hint)
    return 0


def learning_hint(result: dict, scene) -> str | None:
    """What to learn next when the verdict (or its lead's confounded alternatives) says the
    stiffness varies in space: a correction of the principal stretches, the same in every element,
    cannot learn that, a per-element modulus can (`learn --start field`, learning/field.py)."""
    verdict = result.get("verdict") or []
    lead = next((e for e in result.get("effects") or [] if verdict and e.get("name") == verdict[0]), {})
    if "heterogeneity" in verdict or "heterogeneity" in (lead.get("confounded_with") or []):
        return (f"the stiffness varies in space: `matlearn learn {scene} --start field` fits every element "
                "its own Young's modulus before learning the correction")
    return None
