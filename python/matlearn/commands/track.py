"""`matlearn track SCENE --out RUN`: track the model mesh through the point clouds of the scene's
cloud recordings (matlearn.clouds.tracking). Writes, per cloud-only recording <stem>:
RUN/<stem>/surface_%05d.ply (tracked surface per frame, support as `quality`) + times.txt,
RUN/<stem>.pvd + .vtu time series with --vtu, RUN/<stem>_track.json/.csv (per-frame fit
residual), RUN/<stem>_tracked.npz (tracked-marker recording), and RUN/scene.toml, the scene
with cloud recordings replaced by tracked markers, which `matlearn learn` runs on."""
from __future__ import annotations

import sys
from pathlib import Path


def run(args) -> int:
    from ..clouds.ingest import markers_scene
    from ..clouds.tracking import TrackOptions

    opts = TrackOptions(sigma=args.sigma, beta=args.beta, gamma=args.gamma,
                        em_iterations=args.em_iterations, data_weight=args.data_weight)
    from ..clouds.prepare import is_cloud_only
    from ..recording import load_recording
    from ..scene import load_scene

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; track writes a folder")
    if (out / "scene.toml").resolve() == Path(args.scene).resolve():
        raise ValueError(f"--out {out} is the scene's own folder: tracking would replace {args.scene}; "
                         "choose another --out")
    if (out / "scene.toml").exists() and not args.force:
        raise ValueError(f"{out} holds an earlier tracking (scene.toml); use --force to overwrite it "
                         "or choose another --out")
    scene = load_scene(args.scene)
    if not any(is_cloud_only(load_recording(p)) for p, _ in scene.recordings):
        raise ValueError(f"{args.scene}: no recording is point clouds only; nothing to track "
                         "(learn and diagnose use its markers directly)")
    path = markers_scene(args.scene, out, opts, progress=not args.quiet, write_surfaces=not args.no_ply,
                         write_vtu=args.vtu)
    print(f"tracked scene written to {path} (run `matlearn learn {path} --out RUN`)", file=sys.stderr)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("track", help="track the mesh through the scene's point clouds",
                              description=__doc__)
    p.add_argument("scene", help="scene.toml with cloud recordings")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--sigma", type=float, default=None,
                   help="match kernel width (m); default max(cloud_sigma, surface edge / 4)")
    p.add_argument("--beta", type=float, default=0.7, help="position gain of the correction (0, 1]")
    p.add_argument("--gamma", type=float, default=0.3, help="velocity gain of the correction")
    p.add_argument("--em-iterations", type=int, default=2, help="corrections per frame")
    p.add_argument("--data-weight", type=float, default=0.1, help="data vs elastic stiffness")
    p.add_argument("--vtu", action="store_true", help="also write a ParaView .vtu/.pvd series")
    p.add_argument("--no-ply", action="store_true", help="do not write per-frame surface PLYs")
    p.add_argument("--force", action="store_true", help="overwrite an earlier tracking in --out")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)
