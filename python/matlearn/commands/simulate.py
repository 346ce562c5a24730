"""`matlearn simulate`: forward-simulate a scene and write a recording (public .npz format),
optionally a ParaView time series."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from .. import meshes, replay
from ..embedding import embed_points
from ..progress import ProgressBar
from ..recording import Recording, load_recording, save_recording
from ..scene import load_scene, vertices_in_box


def load_correction(run_dir, scene):
    """The learned model of a `matlearn learn` run directory on `scene` (its correction, and the
    fitted base parameters when the run started from the baseline: matlearn.learning.io.scene_model)."""
    if Path(run_dir).is_file():
        raise ValueError(f"--model {run_dir} is a file; pass the run folder that `matlearn learn --out` wrote")
    if not Path(run_dir).is_dir():
        raise FileNotFoundError(f"model run directory not found: {run_dir}")
    try:
        from ..learning.io import scene_model
    except ImportError as err:
        raise ValueError(
            f"--model needs matlearn.learning.load_model, which is not available ({err})"
        ) from err
    return scene_model(scene, run_dir)


def warn_stress_scale(run_dir, scene_path, replaying: bool) -> str | None:
    """The warning for a model whose recordings did not determine its stress scale
    (learning.identify; model.json `stress_scale_determined`), used for anything but a replay of
    the scene it was learned on: another object, or a load (a known force). None otherwise."""
    import json

    from ..learning.io import MODEL_JSON

    info = json.loads((Path(run_dir) / MODEL_JSON).read_text())
    if info.get("stress_scale_determined", True):
        return None
    own = info.get("scene") and Path(info["scene"]).resolve() == Path(scene_path).resolve()
    if own and replaying:
        return None
    fallback = ""
    if not own and info.get("transfer_model"):  # learning.start.learn_best_start: the nominal start's model
        fallback = f" (another scene gets {info['transfer_model']}'s model, learned at your nominal modulus)"
    return (f"warning: {run_dir} was learned from recordings that do not determine its stress scale "
            f"({info.get('stress_scale_message', 'model.json')}); this simulation "
            + ("is of another scene" if not own else "is not a replay of its recordings (a load, gravity)")
            + f", so its deformation may be off by that factor{fallback}")


def load_forces(scene, model, force, box) -> np.ndarray:
    """A total force (N) spread by vertex mass over the free vertices in `box` (default: all)."""
    n = scene.mesh.num_vertices
    f = np.zeros((n, 3))
    if force is None:
        return f
    idx = np.arange(n) if box is None else vertices_in_box(scene.mesh.vertices, np.reshape(box, (2, 3)))
    idx = np.setdiff1d(idx, scene.fixed)
    if len(idx) == 0:
        raise ValueError(f"--load-box {box} contains no free vertex" if box is not None else
                         "--load: every vertex is clamped, so no vertex can carry the load")
    m = np.asarray(model.vertex_mass)[idx]
    f[idx] = np.outer(m / m.sum(), np.asarray(force, float))
    return f


def simulate_scene(scene, model, duration: float, force=None, box=None, release: bool = False,
                   progress=None):
    """Simulate from rest under a constant load, or (`release`) from the static equilibrium under
    the load with the load removed at t = 0. Returns (times (S+1,), X (S+1, n, 3), at_rest)."""
    if not duration > 0:
        raise ValueError(f"--duration must be > 0 (s), got {duration}")
    n = scene.mesh.num_vertices
    f = load_forces(scene, model, force, box)
    integ = scene.integrator(model)
    steps = max(1, int(round(duration / scene.time_step)))
    if release:
        if force is None:
            raise ValueError("--release needs --load (the force to release the body from)")
        integ.static_solve(f, load_steps=5)
        X, _ = integ.simulate(steps, np.zeros((n, 3)), 1, progress=progress)
    else:
        X, _ = integ.simulate(steps, f, 1, progress=progress)
    replay.warn_unconverged(integ, "simulate")
    return scene.time_step * np.arange(steps + 1), X, not release


def _marker_points(scene, args) -> np.ndarray:
    if args.markers:
        p = Path(args.markers)
        if not p.exists():
            raise FileNotFoundError(f"--markers file not found: {p}")
        try:
            pts = np.atleast_2d(np.loadtxt(p, comments="#"))
        except ValueError as err:
            raise ValueError(f"--markers {p}: expected x y z rest positions (m) separated by spaces, "
                             f"one point per line ({err})") from None
        if pts.shape[1] != 3:
            raise ValueError(f"--markers: expected 3 columns (x y z rest positions), got {pts.shape}")
        scene.check_points(pts, "--markers: point")
        return pts
    if not args.all_surface:
        for path in scene.recording_paths():
            rec = load_recording(path)
            if rec.num_markers:
                scene.check_recording(rec, f"recording {Path(path).name} (its markers are the default points)")
                return rec.marker_rest
    return np.asarray(scene.mesh.vertices)[meshes.surface_vertices(scene.mesh)]


def run(args) -> int:
    scene = load_scene(args.scene)
    out = Path(args.out)
    if out.exists() and not args.force:  # before simulating: nothing a user has is replaced silently
        mine = any(out.resolve() == Path(p).resolve() for p in scene.recording_paths())
        raise ValueError(f"--out {out} exists" + (" (it is one of the scene's recordings)" if mine else "")
                         + "; use --force to overwrite it")
    if args.load_box is not None and args.load is None:
        raise ValueError("--load-box selects where --load acts; give --load FX FY FZ too")
    vtu = Path(args.vtu) if args.vtu else None
    if vtu is not None and vtu.exists() and not vtu.is_dir():  # before the recording is written
        raise ValueError(f"--vtu {vtu} is a file; it names a folder for the ParaView series")
    if args.frame_rate is not None and not args.frame_rate > 0:
        raise ValueError(f"--frame-rate must be > 0 (frames per second), got {args.frame_rate}")
    if vtu is not None and (vtu / "frame.pvd").exists() and not args.force:
        raise ValueError(f"--vtu {vtu} already holds a time series (frame.pvd); use --force to replace it")
    model = load_correction(args.model, scene) if args.model else scene.model()
    warning = warn_stress_scale(args.model, args.scene, args.replay is not None) if args.model else None
    if warning:
        print(warning, file=sys.stderr)
    bar = ProgressBar("simulate", enabled=not args.quiet)
    points = _marker_points(scene, args)  # before simulating: bad marker input fails fast
    if args.replay is not None:
        paths = scene.recording_paths()
        if not 0 <= args.replay < len(paths):
            raise ValueError(f"--replay {args.replay}: the scene has {len(paths)} recordings")
        src = load_recording(paths[args.replay])
        scene.check_recording(src, f"recording {args.replay} ({Path(paths[args.replay]).name})")
        try:
            sim_t, X, _ = replay.simulate_recording(scene, model, src, progress=bar)
        except ValueError as err:  # the recording's own problem (its first pose, ...): name it
            raise ValueError(f"recording {args.replay} ({Path(paths[args.replay]).name}): {err}") from None
        times, at_rest = src.times, src.at_rest_initially
        if not (args.markers or args.all_surface):
            points = src.marker_rest
    else:
        duration = args.duration
        if duration is None:
            paths = scene.recording_paths()
            duration = load_recording(paths[0]).duration if paths else 1.0
        sim_t, X, at_rest = simulate_scene(scene, model, duration, args.load, args.load_box,
                                           args.release, bar)
        if abs(sim_t[-1] - duration) > 1e-9 * max(duration, 1.0):
            print(f"note: --duration {duration:g} s is not a whole number of time steps ({scene.time_step:g} s): "
                  f"{sim_t[-1]:g} s simulated", file=sys.stderr)
        if args.frame_rate:
            times = np.arange(0.0, sim_t[-1] + 1e-9, 1.0 / args.frame_rate)
        else:
            times = sim_t
    bar.close()
    emb = embed_points(scene.mesh, points)
    markers = replay.interpolate_frames(sim_t, emb.apply(X), times)
    save_recording(Recording(times, points, markers, at_rest_initially=at_rest), args.out)
    print(f"wrote {args.out}: {len(times)} frames, {len(points)} markers, "
          f"{sim_t[-1] - sim_t[0]:.3f} s simulated")
    if args.vtu:
        from ..vtk_output import write_time_series

        frames = replay.interpolate_frames(sim_t, X, times)
        if (vtu / "frame.pvd").exists():  # replaced (--force): no frames of the older series stay
            for stale in vtu.glob("frame_*.vtu"):
                stale.unlink()
        pvd = write_time_series(vtu, scene.mesh, times, frames)
        print(f"wrote {pvd} ({len(times)} frames)")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="forward-simulate a scene and write a recording (.npz) and optionally VTU frames",
        description="Simulate SCENE with its nominal model (or a learned one, --model) and write "
        "a recording in the public .npz format: markers at the scene's first recording's marker "
        "points by default. Without --release the load is applied from rest for the whole run; "
        "with --release the body starts in static equilibrium under the load, which is then "
        "removed. All values in SI units.",
    )
    p.add_argument("scene", help="scene.toml")
    p.add_argument("--out", required=True, help="output recording (.npz)")
    p.add_argument("--load", nargs=3, type=float, metavar=("FX", "FY", "FZ"),
                   help="total external force (N), spread by mass over --load-box")
    p.add_argument("--load-box", nargs=6, type=float, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="rest-space box of the loaded vertices (default: all free vertices)")
    p.add_argument("--release", action="store_true",
                   help="start from static equilibrium under --load and release it at t = 0")
    p.add_argument("--duration", type=float,
                   help="simulated time (s); default: the first recording's span, else 1 s")
    p.add_argument("--replay", type=int, metavar="INDEX",
                   help="replay the scene's recording INDEX (its initial state, drive and times)")
    p.add_argument("--model", metavar="RUN_DIR", help="use the correction learned in RUN_DIR")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--markers", help="text file of marker rest positions (x y z per line, m)")
    g.add_argument("--all-surface", action="store_true", help="a marker at every surface vertex")
    p.add_argument("--frame-rate", type=float, help="output frames per second (default: every step)")
    p.add_argument("--vtu", metavar="DIR", help="also write a ParaView time series (.pvd + .vtu)")
    p.add_argument("--force", action="store_true", help="overwrite an existing --out (and a --vtu series)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
