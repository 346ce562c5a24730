"""From scans to something `matlearn learn` runs on.

* :func:`markers_scene` -- a copy of a scene in which every recording that has point clouds but
  no markers is replaced by its tracked-marker recording (:func:`.tracking.tracked_markers`),
  written beside a new scene.toml. This is how cloud recordings enter the (marker-based)
  learning loop.
* :func:`make_scene_from_scans` -- real-data ingestion: a closed surface mesh (.obj/.ply/.stl/
  .off, tetrahedralised by TetGen), one or more folders of per-frame .ply/.pcd clouds with
  times.txt, a clamp box and a nominal material guess give a scene (clouds kept as cloud
  recordings in the public .npz format), optionally converted at once with markers_scene.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import meshes
from ..materials import Damping, Material
from ..recording import load_cloud_folder, load_recording, save_recording
from ..scene import Scene, load_scene, save_scene, vertices_in_box
from .tracking import TrackOptions, track, tracked_markers


def as_marker_recordings(scene, recordings, opts: TrackOptions | None = None) -> list:
    """The integration point for learning: each recording that has clouds but no markers is
    replaced by its tracked-marker recording (:func:`.tracking.tracked_markers`); others are
    returned unchanged. A learner calls this on `scene.recordings_with_role(...)` so that
    cloud recordings take the marker path."""
    return [tracked_markers(scene, r, None, opts) if (r.num_markers == 0 and r.has_clouds) else r
            for r in recordings]


def markers_scene(scene_path, out_dir, opts: TrackOptions | None = None, progress: bool = False,
                  write_surfaces: bool = False, write_vtu: bool = False) -> Path:
    """Track every cloud-only recording of the scene and write `out_dir/scene.toml` whose
    recordings are the tracked-marker versions (`<stem>_tracked.npz`; marker recordings are
    referenced unchanged), optionally the tracked surfaces as PLY per frame and/or a VTU series.
    Also writes `out_dir/<stem>_track.json` with the per-frame fit
    residual. Returns the new scene path."""
    scene = load_scene(scene_path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    new_recs = []
    for path, role in scene.recordings:
        rec = load_recording(path)
        if rec.num_markers > 0 or not rec.has_clouds:
            new_recs.append((path, role))
            continue
        res = track(scene, rec, opts, progress=progress)
        mrec = tracked_markers(scene, rec, res, opts)
        dst = out / f"{Path(path).stem}_tracked.npz"
        save_recording(mrec, dst)
        write_track_report(out / f"{Path(path).stem}_track.json", res, scene.object_size)
        if write_surfaces:
            write_surface_sequence(out / Path(path).stem, scene.mesh, res)
        if write_vtu:
            from ..vtk_output import write_time_series

            write_time_series(out / f"{Path(path).stem}_vtu", scene.mesh, res.times, res.X,
                              point_data={"support": res.support})
        new_recs.append((dst, role))
    new = replace(scene, recordings=new_recs)
    return save_scene(new, out / "scene.toml")


def write_track_report(path, res, object_size: float) -> Path:
    """Per-frame fit residual of a tracking run as JSON (and a CSV beside it)."""
    r = res.residual
    seen = (res.support >= 0.25).sum(axis=1)
    doc = {
        "sigma_m": res.sigma,
        "object_size_m": object_size,
        "frames": [
            {"time": float(t), "points": int(p), "rms_m": _f(rm), "mean_m": _f(mm),
             "inlier_fraction": _f(fi), "rms_pct": _f(100 * rm / object_size), "seen_vertices": int(s)}
            for t, p, rm, mm, fi, s in zip(res.times, r["points"], r["rms_m"], r["mean_m"],
                                           r["inlier_fraction"], seen)
        ],
    }
    rms = np.array([f["rms_m"] for f in doc["frames"] if f["rms_m"] is not None])
    doc["summary"] = {"mean_rms_m": float(rms.mean()) if len(rms) else None,
                      "max_rms_m": float(rms.max()) if len(rms) else None,
                      "empty_frames": int(sum(1 for p in r["points"] if p == 0))}
    path = Path(path)
    path.write_text(json.dumps(doc, indent=1))
    lines = ["time,points,rms_m,mean_m,inlier_fraction,seen_vertices"]
    lines += [f"{f['time']:.9g},{f['points']},{f['rms_m']},{f['mean_m']},{f['inlier_fraction']},"
              f"{f['seen_vertices']}" for f in doc["frames"]]
    path.with_suffix(".csv").write_text("\n".join(lines) + "\n")
    return path


def _f(x):
    return None if x is None or not np.isfinite(x) else float(x)


def write_surface_sequence(folder, mesh, res) -> Path:
    """The tracked surface as one binary PLY triangle mesh per frame (`surface_%05d.ply`, with
    the per-vertex support as a `quality` property) plus times.txt."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    F = np.asarray(mesh.surface_faces, np.int32)
    sv = np.unique(F)
    remap = -np.ones(mesh.num_vertices, np.int64)
    remap[sv] = np.arange(len(sv))
    faces = remap[F].astype(np.int32)
    face_rec = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_rec["n"], face_rec["v"] = 3, faces
    for j in range(len(res.times)):
        P = res.X[j, sv]
        vert = np.empty(len(sv), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("quality", "<f8")])
        vert["x"], vert["y"], vert["z"], vert["quality"] = P[:, 0], P[:, 1], P[:, 2], res.support[j, sv]
        head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(sv)}\n"
                "property double x\nproperty double y\nproperty double z\nproperty double quality\n"
                f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
        with open(folder / f"surface_{j:05d}.ply", "wb") as fh:
            fh.write(head.encode("ascii"))
            fh.write(vert.tobytes())
            fh.write(face_rec.tobytes())
    (folder / "times.txt").write_text("".join(f"{t:.9g}\n" for t in res.times))
    return folder


def make_scene_from_scans(surface_mesh, cloud_dirs, fixed_box, out_dir,
                          material: Material | None = None, damping: Damping | None = None,
                          roles=None, cloud_sigma: float | None = None, at_rest_initially=False,
                          time_step: float = 1e-3, gravity=(0.0, -9.81, 0.0),
                          max_volume: float | None = None, min_ratio: float | None = None,
                          track_clouds: bool = True, opts: TrackOptions | None = None,
                          progress: bool = False) -> Path:
    """Build `out_dir/scene.toml` from real scans.

    surface_mesh: closed surface (.obj/.ply/.stl/.off; TetGen'd with max_volume / min_ratio) or
    a tet mesh. cloud_dirs: one folder per recording (per-frame .ply/.pcd + times.txt); roles:
    "train"/"test" per folder (default: the first is train, the rest test). fixed_box: rest-space
    clamp box [[x0,y0,z0],[x1,y1,z1]] (m). material/damping: the nominal guess (default
    co-rotated E = 1e5 Pa, nu = 0.4, 1000 kg/m^3, no damping). cloud_sigma: scanner accuracy (m);
    at_rest_initially: per folder or one bool. The clouds are written as `<folder name>.npz`
    cloud recordings; with track_clouds (default) they are tracked and the returned scene is the
    tracked-marker scene `out_dir/tracked/scene.toml` that `matlearn learn` runs on directly
    (the cloud scene stays at `out_dir/scene.toml`)."""
    cloud_dirs = [Path(d) for d in ([cloud_dirs] if isinstance(cloud_dirs, (str, Path)) else cloud_dirs)]
    if not cloud_dirs:
        raise ValueError("make_scene_from_scans: at least one cloud folder is needed")
    roles = list(roles) if roles is not None else ["train"] + ["test"] * (len(cloud_dirs) - 1)
    if len(roles) != len(cloud_dirs):
        raise ValueError(f"roles: expected {len(cloud_dirs)} entries, got {len(roles)}")
    rest_flags = (list(at_rest_initially) if isinstance(at_rest_initially, (list, tuple))
                  else [bool(at_rest_initially)] * len(cloud_dirs))
    mesh = meshes.load_mesh(surface_mesh, max_volume=max_volume, min_ratio=min_ratio)
    box = np.asarray(fixed_box, float)
    if len(vertices_in_box(mesh.vertices, box)) == 0:
        lo, hi = np.asarray(mesh.vertices).min(0), np.asarray(mesh.vertices).max(0)
        raise ValueError(f"fixed_box {box.tolist()} contains no mesh vertex (mesh bounds {lo.tolist()} .. "
                         f"{hi.tolist()}); check units (m) and the scan's coordinate frame")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    recs = []
    for d, role, rest in zip(cloud_dirs, roles, rest_flags):
        rec = load_cloud_folder(d, cloud_sigma=cloud_sigma)
        rec.at_rest_initially = bool(rest)
        dst = out / f"{d.name}.npz"
        save_recording(rec, dst)
        recs.append((dst.resolve(), role))
    scene = Scene(mesh, material or Material("corotated", 1e5, 0.4, 1000.0), damping or Damping(),
                  vertices_in_box(mesh.vertices, box), time_step, tuple(gravity), recs,
                  fixed_box=box.tolist())
    path = save_scene(scene, out / "scene.toml")
    if not track_clouds:
        return path
    return markers_scene(path, out / "tracked", opts, progress=progress)
