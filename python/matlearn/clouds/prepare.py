"""Cloud recordings as learning input: what `matlearn learn` does with a scene whose recordings
are point clouds (cloud_points / cloud_offsets / cloud_sigma, formats.md).

1. :func:`track_scene` tracks every cloud-only recording with the physics-based tracker
   (:func:`.tracking.track`) and replaces it by its tracked-marker recording; results are cached
   in a folder (the learning run's `tracked/`) together with a fingerprint of the clouds and of
   the tracking options, so a resumed run (`--resume`) reuses them instead of tracking again.
2. :func:`cloud_lambda` chooses the observation weight from the noise of the tracked markers
   and the recorded motion (docs/point_clouds.md, "Observation weight for scans"). The
   space-time solve weighs an observation with w = lam m / h^2 against the inertia m omega^2
   of a deviation at angular frequency omega, so it follows the observations up to the cutoff
   omega_c = sqrt(lam) / h and lets the physics decide above it: a smoothing filter. The
   cutoff is put where the spectrum of the motion falls to that of the noise (the Wiener
   choice for a second-order smoother): a motion of RMS displacement d at dominant frequency
   omega_s (= a_rms / v_rms of the nominal simulation) has a spectral density falling as
   d^2 / omega_s (omega_s / omega)^4 above omega_s, white marker noise of std sigma at frame
   spacing dt has density sigma^2 dt / pi, so

       omega_c = omega_s (pi d^2 / (omega_s sigma^2 dt))^(1/4),  lam = min(1, (omega_c h)^2).

   sigma is the noise of a tracked vertex: the scanner accuracy (the recording's cloud_sigma,
   formats.md; without one, the median per-frame RMS point-to-surface residual of the tracking)
   averaged over the n_pts inlier points that support a seen vertex, sigma_scan / sqrt(n_pts),
   with n_pts = median over frames of (inlier points / seen vertices). (The frame-to-frame
   noise of the tracked markers, :func:`marker_noise`, is reported too but not used: the
   tracker also filters the points through the dynamics, which whitens nothing -- its error is
   correlated in time -- so a white-noise estimate from it is too optimistic.) For exact
   markers sigma -> 0 and lam -> 1, the marker default.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from ..recording import load_recording, save_recording
from .tracking import TrackOptions, track, tracked_markers

CACHE_VERSION = 1


def is_cloud_only(rec) -> bool:
    """A recording with point clouds and no markers (it needs tracking before learning)."""
    return rec.num_markers == 0 and rec.has_clouds


def fingerprint(rec, opts: TrackOptions, scene) -> str:
    """Hash of what the tracked result depends on: the clouds, times, drive, sigma, the tracking
    options and the scene's mesh / material / clamp / time step."""
    h = hashlib.sha1()
    for a in (rec.times, rec.cloud_points, rec.cloud_offsets, np.asarray(scene.mesh.vertices),
              np.asarray(scene.mesh.tets), np.asarray(scene.fixed)):
        h.update(np.ascontiguousarray(a).tobytes())
    if rec.drive is not None:
        h.update(np.ascontiguousarray(rec.drive).tobytes())
    h.update(json.dumps([CACHE_VERSION, asdict(opts), repr(rec.cloud_sigma), bool(rec.at_rest_initially),
                         repr(scene.material), repr(scene.damping), scene.time_step,
                         list(scene.gravity)], default=str).encode())
    return h.hexdigest()


def track_scene(scene, out_dir, opts: TrackOptions | None = None, log=None, progress: bool = False):
    """A copy of `scene` whose cloud-only recordings are replaced by tracked-marker recordings
    written to `out_dir/<i>_<stem>_tracked.npz` (+ `_track.json` per-frame fit residual and
    fingerprint). A cached result with a matching fingerprint is reused. Returns (scene, info)
    with info = {recording path: {"tracked": path, "role", "cached": bool, "sigma_obs_m" (the
    observation noise used for lambda), "tracked_marker_noise_m", "frame_dt_s", tracking residual}}; scenes
    without cloud-only recordings are returned unchanged with info = {}."""
    from .ingest import write_track_report

    opts = opts or TrackOptions()
    say = log or (lambda *a: None)
    out = Path(out_dir)
    new_recs, info = [], {}
    for i, (path, role) in enumerate(scene.recordings):
        rec = load_recording(path)
        if not is_cloud_only(rec):
            new_recs.append((path, role))
            continue
        stem = f"{i}_{Path(path).stem}"
        dst, report = out / f"{stem}_tracked.npz", out / f"{stem}_track.json"
        fp = fingerprint(rec, opts, scene)
        cached = False
        if dst.exists() and report.exists():
            doc = json.loads(report.read_text())
            cached = doc.get("fingerprint") == fp
        if cached:
            say(f"{Path(path).name}: tracked clouds reused from {dst}")
        else:
            out.mkdir(parents=True, exist_ok=True)
            say(f"{Path(path).name}: tracking the mesh through {rec.num_frames} point clouds ({role})")
            res = track(scene, rec, opts, progress=progress)
            mrec = tracked_markers(scene, rec, res, opts)
            write_track_report(report, res, scene.object_size)
            doc = json.loads(report.read_text())
            doc["fingerprint"] = fp
            doc["source"] = str(path)
            report.write_text(json.dumps(doc, indent=1))
            tmp = dst.with_name(dst.stem + ".tmp.npz")
            save_recording(mrec, tmp)
            tmp.replace(dst)
        rms = [f["rms_m"] for f in doc["frames"] if f["rms_m"] is not None]
        mrec = load_recording(dst)
        sigma_scan = float(rec.cloud_sigma) if rec.cloud_sigma else (float(np.median(rms)) if rms else 0.0)
        per = [f["points"] * f["inlier_fraction"] / f["seen_vertices"] for f in doc["frames"]
               if f["points"] and f["seen_vertices"] and f["inlier_fraction"] is not None]
        n_pts = float(np.median(per)) if per else 1.0
        sigma_obs = sigma_scan / np.sqrt(max(n_pts, 1.0))
        dts = np.diff(mrec.times)
        info[str(path)] = {"tracked": str(dst), "role": role, "cached": cached, "sigma_obs_m": sigma_obs,
                           "sigma_scan_m": sigma_scan, "points_per_seen_vertex": n_pts, "tracked_marker_noise_m": marker_noise(mrec), "frame_dt_s": float(np.median(dts)) if len(dts) else None, "cloud_sigma_m": rec.cloud_sigma, "median_track_rms_m": float(np.median(rms)) if rms else None,
                           "summary": doc.get("summary")}
        new_recs.append((dst, role))
    if not info:
        return scene, {}
    return replace(scene, recordings=new_recs), info


def motion_scales(X: np.ndarray, h: float, free: np.ndarray) -> dict:
    """RMS displacement about the mean pose, velocity and acceleration (finite differences at
    step h) of a trajectory (frames, n, 3) over the `free` vertices, and omega_s = a / v."""
    X = np.asarray(X, float)[:, free]
    rms = lambda Y: float(np.sqrt(np.mean(np.sum(Y * Y, axis=-1)))) if Y.size else 0.0  # noqa: E731
    d = rms(X - X.mean(axis=0))
    v = rms(np.diff(X, axis=0) / h)
    a = rms((X[:-2] - 2 * X[1:-1] + X[2:]) / (h * h)) if len(X) > 2 else 0.0
    return {"d_rms_m": d, "v_rms_m_s": v, "a_rms_m_s2": a, "omega_s": a / v if v > 0 else 0.0}


def marker_noise(rec) -> float:
    """Noise std (m) of a marker recording, from fourth differences in time over runs of five
    equally spaced frames in which a marker is seen: for white noise of std sigma the fourth
    difference has std sqrt(70) sigma, while a smooth motion contributes (omega dt)^4 of its
    amplitude (negligible below a tenth of the frame rate). 0 when no such run exists."""
    t = np.asarray(rec.times, float)
    if len(t) < 5:
        return 0.0
    dt = np.diff(t)
    even = np.all(np.abs(dt[np.arange(4)[None] + np.arange(len(t) - 4)[:, None]] - dt[:len(t) - 4, None])
                  <= 0.01 * dt[:len(t) - 4, None], axis=1)
    M = np.asarray(rec.markers, float)
    D4 = M[:-4] - 4 * M[1:-3] + 6 * M[2:-2] - 4 * M[3:-1] + M[4:]  # (T-4, K, 3), NaN if unseen
    ok = even[:, None] & ~np.isnan(D4).any(axis=2)
    if not ok.any():
        return 0.0
    return float(np.sqrt(np.mean(D4[ok] ** 2) / 70.0))


def cloud_lambda(d_rms: float, omega_s: float, sigma: float, frame_dt: float, time_step: float,
                 lam_markers: float = 1.0) -> float:
    """lam = min(lam_markers, (omega_c h)^2), omega_c = omega_s (pi d^2 / (omega_s sigma^2
    dt))^(1/4) (module docstring). Falls back to lam_markers without noise or motion."""
    if not (sigma > 0 and d_rms > 0 and omega_s > 0 and frame_dt > 0):
        return float(lam_markers)
    wc = omega_s * (np.pi * d_rms**2 / (omega_s * sigma**2 * frame_dt)) ** 0.25
    return float(min(lam_markers, (wc * time_step) ** 2))
