"""Worked example for docs/point_clouds.md: from raw scans to a scene `matlearn learn` runs on.

1. Make "real" scans: a silicone-like bar (neo-Hookean, E = 1 MPa) clamped at one end is
   released from a held tip load; a virtual depth camera (one view, 0.5 mm depth noise, 1 %
   outliers, 5 % dropped frames) records it at 200 Hz. Written as a real scanner would: a folder
   of per-frame .ply clouds + times.txt, and a closed surface mesh of the object (bar.obj).
2. Ingest: `make_scene_from_scans(bar.obj, [train_scans, test_scans], clamp box, OUT, nominal
   guess)` tetrahedralises the surface with TetGen, writes cloud recordings and tracks them.
3. Learn: `matlearn learn OUT/tracked/scene.toml --out RUN`.

    python examples/scans_to_scene.py [OUT_DIR]
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from matlearn import meshes
from matlearn.clouds import ScanSettings, default_cameras, write_cloud_folder
from matlearn.clouds.ingest import make_scene_from_scans
from matlearn.clouds.scanner import scan_sequence
from matlearn.materials import Damping, Material, make_model
from matlearn.scene import vertices_in_box
from matlearn.synthetic import Motion, simulate_motion

CLAMP = [[-1.0, -1.0, -1.0], [1e-3, 1.0, 1.0]]
TIP = [[0.18, -1.0, -1.0], [1.0, 1.0, 1.0]]


def fake_scans(out: Path) -> tuple[Path, list[Path]]:
    """Step 1 (stands in for a real capture)."""
    import trimesh

    surf = trimesh.creation.box(extents=(0.2, 0.04, 0.04))
    surf.apply_translation((0.1, 0.0, 0.0))
    surf.export(out / "bar.obj")
    mesh = meshes.load_mesh(out / "bar.obj", max_volume=4e-6)
    truth = make_model(mesh, Material("neo_hookean", 1e6, 0.4, 1000.0), Damping(0.0, 0.005))
    fixed = vertices_in_box(mesh.vertices, CLAMP)
    cams = default_cameras(mesh.vertices, 1)
    dirs = []
    for name, force in (("train_scans", -1.0), ("test_scans", 1.5)):
        motion = Motion("release", "train", 0.3, load={"box": TIP, "force": [0.0, force, 0.0]})
        sim = simulate_motion(mesh, truth, fixed, 1e-3, (0.0, -9.81, 0.0), motion)
        X, times = sim["X"][::5], sim["times"][::5]
        pts, off = scan_sequence(X, mesh.surface_faces, cams,
                                 ScanSettings(noise=5e-4, outlier_fraction=0.01, drop_fraction=0.05, seed=1))
        dirs.append(write_cloud_folder(out / name, times, pts, off))
    return out / "bar.obj", dirs


def main(out_dir="scans_demo") -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    surface, dirs = fake_scans(out)
    scene = make_scene_from_scans(
        surface, dirs, CLAMP, out / "scene",
        material=Material("corotated", 1.2e6, 0.4, 1000.0),  # the nominal guess
        damping=Damping(0.0, 0.005), cloud_sigma=5e-4, max_volume=4e-6,
    )
    report = json.loads((scene.parent / "train_scans_track.json").read_text())
    print(f"tracked scene: {scene}")
    print(f"train fit: mean RMS point-to-surface distance {1e3 * report['summary']['mean_rms_m']:.2f} mm, "
          f"{report['summary']['empty_frames']} dropped frames")
    print(f"next: matlearn learn {scene} --out {out / 'run'}")
    return scene


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "scans_demo")
