"""`matlearn ingest SURFACE --clouds DIR [DIR ...] --fixed-box x0 y0 z0 x1 y1 z1 --out OUT`:
real-data ingestion (docs/point_clouds.md). A closed surface mesh (.obj/.ply/.stl/.off,
tetrahedralised with TetGen), one folder per recording of per-frame .ply/.pcd clouds +
times.txt (the first folder is the train recording, the others test unless --roles says
otherwise), a clamp box and a nominal material guess give OUT/scene.toml (cloud recordings: `matlearn learn
OUT/scene.toml` tracks them itself and chooses lambda from the scan noise) and, after tracking,
OUT/tracked/scene.toml (tracked markers, for inspection; learned with lambda = 1 unless given)."""
from __future__ import annotations

import sys


def run(args) -> int:
    from ..clouds.ingest import make_scene_from_scans
    from ..materials import Damping, Material

    from pathlib import Path

    if (Path(args.out) / "scene.toml").exists() and not args.force:
        raise ValueError(f"{args.out} already holds a scene (scene.toml); use --force to overwrite it "
                         "or choose another --out")
    box = [args.fixed_box[:3], args.fixed_box[3:]]
    path = make_scene_from_scans(
        args.surface, args.clouds, box, args.out,
        material=Material(args.model, args.youngs_modulus, args.poisson_ratio, args.density),
        damping=Damping(args.alpha_mass, args.alpha_stiffness), roles=args.roles,
        cloud_sigma=args.cloud_sigma, at_rest_initially=args.at_rest, time_step=args.time_step,
        max_volume=args.max_volume, track_clouds=not args.no_track, progress=not args.quiet)
    print(f"scene written to {path}" + ("" if args.no_track else f" (run `matlearn learn {path} --out RUN`)"),
          file=sys.stderr)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("ingest", help="make a scene from a surface mesh and folders of scans",
                              description=__doc__)
    p.add_argument("surface", help="closed surface mesh (.obj/.ply/.stl/.off) or a tet mesh, in m")
    p.add_argument("--clouds", nargs="+", required=True, help="folders of .ply/.pcd + times.txt")
    p.add_argument("--roles", nargs="+", choices=("train", "test"), default=None,
                   help="role per folder (default: first train, rest test)")
    p.add_argument("--fixed-box", nargs=6, type=float, required=True, metavar="X",
                   help="clamp box x0 y0 z0 x1 y1 z1 (m, rest frame)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--model", default="corotated", choices=("corotated", "neo_hookean", "stvk"),
                   help="nominal material law (default corotated)")
    p.add_argument("--youngs-modulus", type=float, default=1e5, help="Pa")
    p.add_argument("--poisson-ratio", type=float, default=0.4, help="dimensionless")
    p.add_argument("--density", type=float, default=1000.0, help="kg/m^3")
    p.add_argument("--alpha-mass", type=float, default=0.0, help="Rayleigh mass coefficient (1/s)")
    p.add_argument("--alpha-stiffness", type=float, default=0.0, help="Rayleigh stiffness coefficient (s)")
    p.add_argument("--cloud-sigma", type=float, default=None, help="scanner accuracy (m)")
    p.add_argument("--at-rest", action="store_true", help="recordings start at rest (not held deformed)")
    p.add_argument("--time-step", type=float, default=1e-3, help="s")
    p.add_argument("--max-volume", type=float, default=None, help="TetGen volume bound (m^3)")
    p.add_argument("--no-track", action="store_true", help="only write the cloud scene")
    p.add_argument("--force", action="store_true", help="overwrite a scene already in --out")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)
