"""A virtual depth scanner: ray-cast the simulated surface from one to three pinhole cameras per
frame, keep the visible hits, add noise and outliers, optionally drop frames (method.md section 7).

Noise model (stated, seeded): each hit is displaced along its ray by N(0, noise^2) (a depth
sensor's error is mostly along the line of sight); `outlier_fraction` of the returned points of a
frame are replaced by points uniform in the frame's bounding box grown by 20 % of the object
size; with `drop_fraction` each frame after the first is, independently, lost (an empty cloud).
Ray casting uses open3d's `RaycastingScene` (CPU, BVH in C++), one build per frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..recording import Recording, save_recording


@dataclass
class Camera:
    """A pinhole camera at `eye` looking at `center` (m), vertical field of view `fov_deg`,
    `width` x `height` pixels."""

    eye: tuple
    center: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov_deg: float = 40.0
    width: int = 96
    height: int = 72

    def rays(self) -> np.ndarray:
        """(height*width, 6) rays: origin and unit direction."""
        import open3d as o3d

        eye, center, up = (np.asarray(v, float) for v in (self.eye, self.center, self.up))
        fwd = center - eye
        if np.linalg.norm(np.cross(fwd, up)) < 1e-9 * np.linalg.norm(fwd):
            raise ValueError(f"camera up {self.up} is parallel to the viewing direction")
        r = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg=float(self.fov_deg), center=center.tolist(), eye=eye.tolist(), up=up.tolist(),
            width_px=int(self.width), height_px=int(self.height),
        ).numpy().reshape(-1, 6).astype(np.float64)
        r[:, 3:] /= np.linalg.norm(r[:, 3:], axis=1, keepdims=True)
        return r


def default_cameras(vertices: np.ndarray, views: int = 1, distance: float = 2.5,
                    resolution: tuple = (96, 72), fov_deg: float = 40.0) -> list[Camera]:
    """1-3 cameras around the rest shape's bounding box, `distance` x object size from its
    centre. View 1 looks from the front (+z, a little above); views 2 and 3 are 120 degrees apart
    around the vertical axis, so three views together see (almost) the whole surface."""
    if views not in (1, 2, 3):
        raise ValueError(f"views must be 1, 2 or 3, got {views}")
    V = np.asarray(vertices, float)
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre, size = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    cams = []
    for i in range(views):
        a = np.pi / 2 + i * 2 * np.pi / 3
        d = np.array([np.cos(a), 0.45, np.sin(a)])
        d /= np.linalg.norm(d)
        cams.append(Camera(tuple(centre + distance * size * d), tuple(centre), (0.0, 1.0, 0.0),
                           fov_deg, int(resolution[0]), int(resolution[1])))
    return cams


def _raycast_scene(vertices, faces):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(vertices, np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32))
    )
    return scene


def _hits(scene, r: np.ndarray) -> np.ndarray:
    import open3d as o3d

    t = scene.cast_rays(o3d.core.Tensor(r.astype(np.float32)))["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t)
    return r[hit, :3] + t[hit, None] * r[hit, 3:]


def scan_surface(vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera]) -> np.ndarray:
    """Noise-free visible surface points (N, 3) of one pose seen by `cameras`."""
    scene = _raycast_scene(vertices, faces)
    return np.concatenate([_hits(scene, c.rays()) for c in cameras])


@dataclass
class ScanSettings:
    """Scanner accuracy and defects. noise: depth noise std (m) along the ray; outlier_fraction:
    share of each frame's points replaced by uniform outliers; drop_fraction: probability that a
    frame (after the first) is lost; seed for all randomness."""

    noise: float = 1e-3
    outlier_fraction: float = 0.0
    drop_fraction: float = 0.0
    seed: int = 0

    def __post_init__(self):
        if self.noise < 0:
            raise ValueError(f"noise must be >= 0 (m), got {self.noise}")
        if not 0 <= self.outlier_fraction < 1:
            raise ValueError(f"outlier_fraction must lie in [0, 1), got {self.outlier_fraction}")
        if not 0 <= self.drop_fraction < 1:
            raise ValueError(f"drop_fraction must lie in [0, 1), got {self.drop_fraction}")


def scan_sequence(positions: np.ndarray, faces: np.ndarray, cameras: list[Camera],
                  settings: ScanSettings | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Scan every pose of `positions` (T, n, 3) (surface `faces` (F, 3) index its vertices).
    Returns (cloud_points (N, 3), cloud_offsets (T+1,)) in the recording format."""
    s = settings or ScanSettings()
    X = np.asarray(positions, float)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"positions: expected shape (T, n, 3), got {X.shape}")
    if not cameras:
        raise ValueError("at least one camera is needed")
    rng = np.random.default_rng(s.seed)
    rays = [c.rays() for c in cameras]
    size = float(np.linalg.norm(np.ptp(X[0], axis=0)))
    clouds = []
    for t in range(len(X)):
        if t > 0 and rng.random() < s.drop_fraction:
            clouds.append(np.zeros((0, 3)))
            continue
        pts = []
        scene = _raycast_scene(X[t], faces)
        for cam, r in zip(cameras, rays):
            p = _hits(scene, r)
            if len(p) and s.noise > 0:
                eye = np.asarray(cam.eye, float)
                d = p - eye
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                p = p + rng.normal(0.0, s.noise, (len(p), 1)) * d
            pts.append(p)
        p = np.concatenate(pts)
        n_out = int(round(s.outlier_fraction * len(p)))
        if n_out:
            lo, hi = X[t].min(axis=0) - 0.2 * size, X[t].max(axis=0) + 0.2 * size
            idx = rng.choice(len(p), n_out, replace=False)
            p[idx] = lo + rng.random((n_out, 3)) * (hi - lo)
        clouds.append(p)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)
    return np.concatenate(clouds), offsets


def cloud_recording(times, points, offsets, sigma: float, at_rest_initially: bool = False,
                    base: Recording | None = None) -> Recording:
    """A Recording with the clouds (and, from `base`, its markers and drive points if any)."""
    kw = {}
    if base is not None:
        kw = dict(marker_rest=base.marker_rest, markers=base.markers, drive_rest=base.drive_rest,
                  drive=base.drive)
    return Recording(np.asarray(times, float), cloud_points=points, cloud_offsets=offsets,
                     cloud_sigma=float(sigma), at_rest_initially=at_rest_initially, **kw)


def write_ply_points(path, points: np.ndarray) -> None:
    """A binary little-endian PLY with float64 x, y, z vertices only."""
    pts = np.ascontiguousarray(points, dtype="<f8").reshape(-1, 3)
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n"
            "property double x\nproperty double y\nproperty double z\nend_header\n")
    with open(path, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(pts.tobytes())


def write_cloud_folder(folder, times, points, offsets, skip_empty: bool = True) -> Path:
    """Write frame t's cloud as `frame_%05d.ply` plus `times.txt` (the real-scanner layout read
    by `matlearn.recording.load_cloud_folder`). Empty (dropped) frames are left out, so the
    folder holds only frames a scanner actually delivered."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    times = np.asarray(times, float)
    kept = []
    for t in range(len(times)):
        c = points[offsets[t] : offsets[t + 1]]
        if skip_empty and len(c) == 0:
            continue
        write_ply_points(folder / f"frame_{t:05d}.ply", c)
        kept.append(times[t])
    (folder / "times.txt").write_text("".join(f"{x:.9g}\n" for x in kept))
    return folder


def scan_recording(rec_positions: np.ndarray, times, faces, cameras, settings: ScanSettings,
                   path=None, folder=None, at_rest_initially: bool = False,
                   base: Recording | None = None) -> Recording:
    """Scan a simulated trajectory sampled at `times` and return (and optionally save as `.npz`
    and/or a `.ply` folder) the cloud recording; `cloud_sigma` is the scanner's noise level
    (at least 1e-4 of the object size, so noise-free scans still have a usable sigma)."""
    pts, off = scan_sequence(rec_positions, faces, cameras, settings)
    size = float(np.linalg.norm(np.ptp(np.asarray(rec_positions)[0], axis=0)))
    sigma = max(settings.noise, 1e-4 * size)
    rec = cloud_recording(times, pts, off, sigma, at_rest_initially, base)
    if path is not None:
        save_recording(rec, path)
    if folder is not None:
        write_cloud_folder(folder, times, pts, off)
    return rec
