"""Synthetic cases with known truth: a "real" object (truth mesh, material, damping) is simulated
through a set of motions, its surface markers are recorded in the public format, and a scene is
written with the *nominal* model on the (possibly coarser) model mesh. The truth goes to
`truth.json` beside the scene; learners and diagnosers must never read it.

Motions:
* ``release``: the body is held in static equilibrium under a load (a force spread over the
  vertices of a box by mass) and/or a twist (tangential forces of a box's vertices whose moment
  about their centre of mass is the given torque, zero net force), then released at t = 0.
* ``drive``: the vertices of a rest-space box follow keyframed displacements [(t, (dx, dy, dz))],
  eased between keyframes (half-cosine: zero velocity at every keyframe); before the first and
  after the last keyframe the displacement is held. A drive may also start from a held load.
* ``flick``: the vertices of a box get an initial velocity (a tap) from rest (or from a held
  load); the body swings and the recording starts at the least kinetic energy within the
  pre-roll after the first energy peak, so it begins, like a release, from a deformed pose nearly
  at rest (what remains of the motion is part of the experiment).
* ``release`` with neither load nor twist is a drop: the body starts at its rest shape and
  sags under gravity.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import _core, meshes
from .materials import Damping, Material, make_model
from .progress import ProgressBar
from .recording import Recording, save_recording
from .replay import interpolate_frames
from .scene import DEFAULT_GRAVITY, Scene, save_scene, vertices_in_box

KINDS = ("release", "drive", "flick")


@dataclass
class Motion:
    """One recorded motion. load = {"box": [[x0,y0,z0],[x1,y1,z1]], "force": [fx, fy, fz]} (total
    N); twist = {"box": ..., "torque": [tx, ty, tz]} (N m); drive = {"box": ...,
    "keyframes": [[t, [dx, dy, dz]], ...]} (s, m)."""

    kind: str = "release"
    role: str = "train"
    duration: float = 0.5
    load: dict | None = None
    twist: dict | None = None
    drive: dict | None = None
    load_steps: int = 5
    velocity: dict | None = None
    max_preroll: float = 0.3

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"Motion.kind must be one of {KINDS}, got {self.kind!r}")
        if self.role not in ("train", "test"):
            raise ValueError(f"Motion.role must be 'train' or 'test', got {self.role!r}")
        if not self.duration > 0:
            raise ValueError(f"Motion.duration must be > 0 (s), got {self.duration}")
        if self.kind == "flick" and not (self.velocity and "box" in self.velocity
                                         and "velocity" in self.velocity):
            raise ValueError("a 'flick' motion needs velocity={'box': ..., 'velocity': [vx, vy, vz]}")
        if self.kind == "drive" and not self.drive:
            raise ValueError("a 'drive' motion needs drive={'box': ..., 'keyframes': [...]}")
        if self.drive:
            kf = self.drive.get("keyframes")
            if not kf or "box" not in self.drive:
                raise ValueError("drive needs 'box' and a non-empty 'keyframes' list")
            ts = [float(k[0]) for k in kf]
            if any(b <= a for a, b in zip(ts, ts[1:])):
                raise ValueError("drive keyframe times must be strictly increasing")
        for name in ("load", "twist"):
            spec = getattr(self, name)
            key = "force" if name == "load" else "torque"
            if spec is not None and ("box" not in spec or key not in spec):
                raise ValueError(f"{name} needs 'box' and '{key}'")


def drive_displacement(keyframes, t) -> np.ndarray:
    """Eased keyframe displacement (len(t), 3) at times t."""
    t = np.atleast_1d(np.asarray(t, float))
    kt = np.array([float(k[0]) for k in keyframes])
    kd = np.array([np.asarray(k[1], float) for k in keyframes]).reshape(len(kt), 3)
    if len(kt) == 1:
        return np.repeat(kd, len(t), axis=0)
    i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(kt) - 2)
    s = np.clip((t - kt[i]) / (kt[i + 1] - kt[i]), 0.0, 1.0)
    w = (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    return kd[i] + w * (kd[i + 1] - kd[i])


def _box_vertices(mesh, box, what, exclude=()):
    idx = np.setdiff1d(vertices_in_box(mesh.vertices, box), np.asarray(exclude, np.int64))
    if len(idx) == 0:
        raise ValueError(f"{what} box {box} contains no free vertex of the mesh")
    return idx


def hold_forces(mesh, vertex_mass, motion: Motion, fixed=()) -> np.ndarray:
    """External forces (n, 3) holding the initial pose: load spread by mass, plus the twist."""
    V = np.asarray(mesh.vertices)
    m = np.asarray(vertex_mass, float)
    f = np.zeros_like(V)
    if motion.load is not None:
        idx = _box_vertices(mesh, motion.load["box"], "load", fixed)
        f[idx] += np.outer(m[idx] / m[idx].sum(), np.asarray(motion.load["force"], float))
    if motion.twist is not None:
        idx = _box_vertices(mesh, motion.twist["box"], "twist", fixed)
        mi = m[idx]
        r = V[idx] - (mi[:, None] * V[idx]).sum(0) / mi.sum()
        # f_i = m_i w x r_i has zero net force and moment I w; solve I w = torque.
        inertia = (mi * (r**2).sum(1)).sum() * np.eye(3) - np.einsum("i,ij,ik->jk", mi, r, r)
        w = np.linalg.pinv(inertia) @ np.asarray(motion.twist["torque"], float)
        f[idx] += mi[:, None] * np.cross(w, r)
    return f


def simulate_motion(mesh, model, fixed, time_step: float, gravity, motion: Motion, progress=None):
    """Simulate one motion on `mesh` with `model`. Returns dict(times (S+1,), X (S+1, n, 3),
    at_rest_initially, drive_idx (D,), drive_keyframes)."""
    n = mesh.num_vertices
    V = np.asarray(mesh.vertices, float)
    fixed = np.asarray(fixed, np.int64)
    integ = _core.time.Integrator(model, fixed, time_step, np.asarray(gravity, float))
    f_hold = hold_forces(mesh, model.vertex_mass, motion, fixed)
    steps = int(round(motion.duration / time_step))
    times = time_step * np.arange(steps + 1)
    x = V.copy()
    didx = np.zeros(0, np.int64)
    if motion.drive:
        didx = _box_vertices(mesh, motion.drive["box"], "drive", fixed)
        integ.set_prescribed(didx)
        x[didx] += drive_displacement(motion.drive["keyframes"], [0.0])[0]
    held = bool(np.any(f_hold != 0) or np.any(x != V))
    integ.set_state(x, np.zeros((n, 3)))
    if held:
        integ.static_solve(f_hold, load_steps=motion.load_steps)
    zero = np.zeros((n, 3))
    if motion.kind == "flick":
        tap = _box_vertices(mesh, motion.velocity["box"], "velocity", fixed)
        v0 = np.zeros((n, 3))
        vdir = np.asarray(motion.velocity["velocity"], float)
        v0[tap] = vdir
        integ.set_state(np.array(integ.x), v0)
        pre = max(1, int(round(motion.max_preroll / time_step)))
        Xp, Vp = integ.simulate(pre, zero, 1)
        # start at the least kinetic energy after the swing's first energy peak
        ke = (np.asarray(model.vertex_mass)[None] * (Vp**2).sum(axis=2)).sum(axis=1)
        peak = int(np.argmax(ke[: max(2, len(ke) // 3)]))
        k = peak + int(np.argmin(ke[peak:]))
        integ.set_state(Xp[k], Vp[k])
        held = True
    if len(didx):
        targets = V[didx][None] + drive_displacement(motion.drive["keyframes"], times[1:])[:, None]
        X, _ = integ.simulate_constrained(targets, zero, progress=progress)
    else:
        X, _ = integ.simulate(steps, zero, 1, progress=progress)
    return {"times": times, "X": X, "at_rest_initially": not held, "drive_idx": didx}


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    return x


def make_case(out_dir, name: str, truth_mesh, truth_material: Material, truth_damping: Damping,
              model_mesh, nominal_material: Material, nominal_damping: Damping, fixed_box,
              motions: list, marker_fraction: float = 1.0, noise: float = 0.0, seed: int = 0,
              frame_rate: float | None = None, time_step: float = 1e-3, gravity=DEFAULT_GRAVITY,
              truth_correction=None, truth_model=None, truth_fixed_box=None, dropout: float = 0.0,
              extra: dict | None = None, progress: bool = False, mesh_file: str = "mesh.vtu",
              simulate_truth=None) -> Path:
    """Build case `out_dir/name/` and return the path of its `scene.toml`.

    The truth (truth_mesh with truth_material/damping, optionally a correction or a ready
    `truth_model` on truth_mesh, clamped by truth_fixed_box or fixed_box) is simulated at
    `time_step` through every motion. Markers: a seeded random `marker_fraction` of the truth
    surface vertices (at least 3), the same set in every recording, sampled at `frame_rate` Hz
    (default: every step), with Gaussian noise of std `noise` (m) and a seeded fraction `dropout`
    of marker-frames unseen (NaN). The scene gets the nominal model on model_mesh and fixed_box;
    recordings are named <role>_<i>.npz. `extra` is merged into truth.json.

    `simulate_truth` replaces :func:`simulate_motion` (same arguments and result) for a "reality"
    the model classes cannot express (e.g. hysteresis, a moving support)."""
    if not motions:
        raise ValueError("make_case needs at least one Motion")
    if not 0 < marker_fraction <= 1:
        raise ValueError(f"marker_fraction must lie in (0, 1], got {marker_fraction}")
    if noise < 0 or not 0 <= dropout < 1:
        raise ValueError("noise must be >= 0 and dropout in [0, 1)")
    if frame_rate is not None and not frame_rate > 0:
        raise ValueError(f"frame_rate must be > 0 (Hz), got {frame_rate}")
    case = Path(out_dir) / name
    case.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)

    truth_box = truth_fixed_box if truth_fixed_box is not None else fixed_box
    truth_fixed = vertices_in_box(truth_mesh.vertices, truth_box)
    model_fixed = vertices_in_box(model_mesh.vertices, fixed_box)
    if len(model_fixed) == 0 or len(truth_fixed) == 0:
        raise ValueError(f"fixed_box {fixed_box} contains no vertex of the truth or model mesh")
    if truth_model is None:
        truth_model = make_model(truth_mesh, truth_material, truth_damping, truth_correction)

    surf = meshes.surface_vertices(truth_mesh)
    k = int(min(len(surf), max(3, round(marker_fraction * len(surf)))))
    marker_ids = np.sort(rng.choice(surf, size=k, replace=False))
    marker_rest = np.asarray(truth_mesh.vertices)[marker_ids]

    recordings, rec_info, counts = [], [], {"train": 0, "test": 0}
    for i, motion in enumerate(motions):
        bar = ProgressBar(f"{name} motion {i} ({motion.kind})", enabled=progress)
        sim = (simulate_truth or simulate_motion)(truth_mesh, truth_model, truth_fixed, time_step,
                                                  gravity, motion, bar)
        bar.close()
        if frame_rate is None:
            times = sim["times"]
        else:
            times = np.arange(0.0, motion.duration + 1e-9, 1.0 / frame_rate)
        markers = interpolate_frames(sim["times"], sim["X"][:, marker_ids], times)
        if noise > 0:
            markers = markers + rng.normal(0.0, noise, markers.shape)
        if dropout > 0:
            hide = rng.random(markers.shape[:2]) < dropout
            if hide.all():
                hide[0, 0] = False
            markers[hide] = np.nan
        kwargs = {}
        if len(sim["drive_idx"]):
            drest = np.asarray(truth_mesh.vertices)[sim["drive_idx"]]
            disp = drive_displacement(motion.drive["keyframes"], times)
            kwargs = {"drive_rest": drest, "drive": drest[None] + disp[:, None]}
        rec = Recording(times, marker_rest, markers, at_rest_initially=sim["at_rest_initially"], **kwargs)
        fname = f"{motion.role}_{counts[motion.role]}.npz"
        counts[motion.role] += 1
        save_recording(rec, case / fname)
        recordings.append((case / fname, motion.role))
        rec_info.append({"file": fname, "role": motion.role, "motion": asdict(motion),
                         "frames": len(times), "at_rest_initially": sim["at_rest_initially"]})

    scene = Scene(model_mesh, nominal_material, nominal_damping, model_fixed, time_step, gravity,
                  recordings, fixed_box=[list(map(float, r)) for r in fixed_box])
    path = save_scene(scene, case / "scene.toml", mesh_file=mesh_file)

    cell = {}
    if truth_material is not None:
        for key in ("youngs_modulus", "poisson_ratio", "density"):
            cell[key] = np.broadcast_to(np.asarray(getattr(truth_material, key), float),
                                        (truth_mesh.num_tets,)).copy()
    meshes.save_mesh(truth_mesh, case / "truth_mesh.vtu", cell_data=cell)
    truth = {
        "name": name,
        "truth_material": asdict(truth_material) if truth_material is not None else None,
        "truth_damping": asdict(truth_damping) if truth_damping is not None else None,
        "truth_has_correction": truth_correction is not None,
        "nominal_material": asdict(nominal_material),
        "nominal_damping": asdict(nominal_damping),
        "truth_mesh": {"file": "truth_mesh.vtu", "vertices": truth_mesh.num_vertices,
                       "tets": truth_mesh.num_tets},
        "model_mesh": {"file": mesh_file, "vertices": model_mesh.num_vertices,
                       "tets": model_mesh.num_tets},
        "fixed_box": fixed_box,
        "truth_fixed_box": truth_box,
        "time_step": time_step,
        "gravity": list(gravity),
        "marker_fraction": marker_fraction,
        "marker_truth_vertices": marker_ids,
        "noise": noise,
        "dropout": dropout,
        "frame_rate": frame_rate,
        "seed": seed,
        "recordings": rec_info,
        "extra": extra or {},
    }
    (case / "truth.json").write_text(json.dumps(_jsonable(truth), indent=1))
    return path
