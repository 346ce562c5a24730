"""Replaying a recording with a model: initial state, forward simulation, predicted markers and
the trajectory error (% of object size) used to score every model in matlearn.

Initial state. A recording with `at_rest_initially` starts from the rest shape with zero
velocity. Otherwise the start is a *held pose*: the vertices nearest the markers seen in frame 0
(and the driven vertices) are prescribed at their observed displacement, the rest of the body
is solved to static equilibrium (gravity included, loaded in increments), and the body is
released from there; a few refinement passes then shift each marker's vertex by the marker's
remaining misfit so that markers between vertices are matched too. The initial velocity is zero by default, the paper's setting (objects are
released from a held, deformed pose); `velocity="estimate"` instead estimates it by finite
differences of the equilibrium shapes matched to frames 0 and 1, for recordings that start
mid-motion. `start="released"` (release.py) replaces the held pose by smooth hold forces fitted
to frame 0, chosen and refined on the first frames after the release: the start every model is
scored from (SCORE_START, :func:`score`).

Drive points (recording extension keys `drive_rest`/`drive`) become prescribed vertices: the
model vertices within half the drive points' spacing of some drive point (at least the nearest
vertex of each drive point), following the drive displacement of their nearest drive points
(inverse-distance weighted), interpolated linearly in time between recording samples.
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial import cKDTree

from .embedding import Embedding, embed_points
from .parallel import pmap
from .recording import Recording


class NonConvergenceWarning(RuntimeWarning):
    """Some implicit steps of a simulation stopped at the Newton iteration limit without meeting
    the tolerance; they were kept as they were, so the trajectory may be inaccurate."""


def warn_unconverged(integ, what: str) -> int:
    """Warn (NonConvergenceWarning) when `integ` kept steps whose Newton iteration did not
    converge since its last set_state; returns their number. Linearised integrators
    (max_newton = 1) never count any."""
    n = int(integ.unconverged_steps)
    if n:
        warnings.warn(f"{what}: {n} of {integ.steps_taken} implicit steps stopped at the Newton "
                      f"iteration limit without converging (kept as they were), so the trajectory may "
                      f"be inaccurate; try a smaller time step or check the model's parameters",
                      NonConvergenceWarning, stacklevel=3)
    return n


# ---------------------------------------------------------------------------- drive points
def drive_vertices(scene, rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    """Driven model vertices (k,) and their positions at the recording times (T, k, 3).
    Empty (0,), (T, 0, 3) when the recording has no drive points."""
    T = rec.num_frames
    if not rec.has_drive:
        return np.zeros(0, np.int64), np.zeros((T, 0, 3))
    V = np.asarray(scene.mesh.vertices)
    tree = cKDTree(rec.drive_rest)
    if len(rec.drive_rest) > 1:
        spacing = np.median(tree.query(rec.drive_rest, k=2)[0][:, 1])
    else:
        spacing = 0.0
    dist, _ = tree.query(V)
    chosen = set(np.flatnonzero(dist <= 0.5 * spacing + 1e-9 * scene.object_size).tolist())
    chosen |= set(cKDTree(V).query(rec.drive_rest)[1].tolist())
    fixed = set(np.asarray(scene.fixed).tolist())
    idx = np.array(sorted(chosen - fixed), dtype=np.int64)
    if len(idx) == 0:
        raise ValueError("drive points map only to clamped vertices; nothing to drive")
    disp = rec.drive - rec.drive_rest[None]  # (T, D, 3)
    kq = min(4, len(rec.drive_rest))
    d, nb = tree.query(V[idx], k=kq)
    d, nb = d.reshape(len(idx), kq), nb.reshape(len(idx), kq)
    w = 1.0 / np.maximum(d, 1e-12 * scene.object_size) ** 2
    exact = d[:, 0] <= 1e-9 * scene.object_size
    w[exact] = 0.0
    w[exact, 0] = 1.0
    w /= w.sum(axis=1, keepdims=True)
    targets = V[idx][None] + np.einsum("kj,tkjd->tkd", w, disp[:, nb])
    return idx, targets


def interpolate_frames(times: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Linear interpolation of values (T, ...) sampled at `times` to the times `at` (held
    constant outside the sampled span)."""
    times = np.asarray(times, float)
    at = np.asarray(at, float)
    if len(times) == 1:
        return np.repeat(values[:1], len(at), axis=0)
    i = np.clip(np.searchsorted(times, at, side="right") - 1, 0, len(times) - 2)
    w = np.clip((at - times[i]) / (times[i + 1] - times[i]), 0.0, 1.0)
    w = w.reshape((-1,) + (1,) * (values.ndim - 1))
    return (1 - w) * values[i] + w * values[i + 1]


# ---------------------------------------------------------------------------- initial state
STARTS = ("held", "released")
# The initial state every model is scored with (score, the learning loop's test errors): the
# released start (release.py), which uses the frames of the first 1/8 of the model's lowest
# period after the release besides frame 0.
SCORE_START = "released"


def _held_pose(scene, model, rec: Recording, frame: int, embedding: Embedding, integ=None,
               refine: int = 3):
    """Static equilibrium with marker-nearest and driven vertices prescribed at frame `frame`.
    `refine` passes then move each marker's vertex by the marker's remaining misfit (divided by
    the vertex's weight) and re-solve, so off-vertex markers are matched too."""
    V = np.asarray(scene.mesh.vertices)
    fixed = set(np.asarray(scene.fixed).tolist())
    seen = rec.seen[frame]
    near = embedding.nearest_vertices()[seen]
    disp = rec.markers[frame, seen] - rec.marker_rest[seen]
    # Average the displacement over markers sharing a nearest vertex.
    uniq, inv = np.unique(near, return_inverse=True)
    vdisp = np.zeros((len(uniq), 3))
    np.add.at(vdisp, inv, disp)
    vdisp /= np.bincount(inv, minlength=len(uniq))[:, None]
    didx, dtargets = drive_vertices(scene, rec)
    target = dict(zip(uniq.tolist(), (V[uniq] + vdisp)))
    target.update(zip(didx.tolist(), dtargets[frame]))  # drive wins over markers
    idx = np.array(sorted(set(target) - fixed), dtype=np.int64)
    n = scene.mesh.num_vertices
    if len(idx) == 0:
        return V.copy()
    tpos = np.array([target[i] for i in idx])
    if len(idx) + len(fixed) == n:  # every free vertex observed: nothing to solve for
        x = V.copy()
        x[idx] = tpos
        return x
    integ = scene.integrator(model) if integ is None else integ
    integ.set_prescribed(idx)
    # Prescribe in increments so a large held deformation does not invert elements at once; where
    # an increment's Newton solve fails, the increments are made 4x finer (twice at most)
    max_disp = np.abs(tpos - V[idx]).max()
    incs = int(np.clip(np.ceil(max_disp / (0.05 * scene.object_size)), 1, 20))
    zero_f = np.zeros((n, 3))
    for attempt in range(3):
        x = V.copy()
        try:
            for s in range(1, incs + 1):
                x[idx] = V[idx] + (s / incs) * (tpos - V[idx])
                integ.set_state(x, np.zeros((n, 3)))
                integ.static_solve(zero_f, load_steps=1)
                x = np.array(integ.x)
            break
        except RuntimeError:
            if attempt == 2:
                integ.set_prescribed(np.zeros(0, np.int64))
                raise
            incs *= 4
    # Refinement: only marker vertices (not driven, not clamped) are corrected. A pass whose
    # solve fails (a correction divided by a small barycentric weight can invert the small
    # elements of a fine mesh: independent seed 13's cylinder refined 1:8, a velocity probe's
    # held pose) is undone and the refinement stops there: the pose is the last one solved.
    pos = {v: i for i, v in enumerate(idx.tolist())}
    rows = np.array([pos.get(v, -1) for v in uniq.tolist()])
    movable = (rows >= 0) & ~np.isin(uniq, didx)
    wmax = embedding.bary.max(axis=1)[seen]
    for _ in range(refine if movable.any() else 0):
        misfit = (rec.markers[frame, seen] - embedding.apply(x)[seen]) / wmax[:, None]
        corr = np.zeros((len(uniq), 3))
        np.add.at(corr, inv, misfit)
        corr /= np.bincount(inv, minlength=len(uniq))[:, None]
        trial = x.copy()
        trial[idx[rows[movable]]] += corr[movable]
        integ.set_state(trial, np.zeros((n, 3)))
        try:
            integ.static_solve(zero_f, load_steps=1)
        except RuntimeError:
            break
        x = np.array(integ.x)
    integ.set_prescribed(np.zeros(0, np.int64))
    return x


def initial_state(scene, model, rec: Recording, embedding: Embedding | None = None,
                  velocity: str = "zero", refine: int = 3, start: str = "held") -> tuple[np.ndarray, np.ndarray]:
    """(x0, v0), each (n, 3), at rec.times[0]; see the module docstring. velocity: "zero" or
    "estimate"; refine: misfit-correction passes of the held pose (0 = nearest vertices only);
    start: "held" (the held pose) or "released" (:func:`release.released_start` from the held
    pose: smooth hold forces and the first frames after the release; velocity zero only)."""
    n = scene.mesh.num_vertices
    V = np.asarray(scene.mesh.vertices, float)
    if velocity not in ("zero", "estimate"):
        raise ValueError(f"velocity must be 'zero' or 'estimate', got {velocity!r}")
    if start not in STARTS:
        raise ValueError(f"start must be one of {STARTS}, got {start!r}")
    if start == "released" and velocity != "zero":
        raise ValueError("start='released' estimates a pose released at rest: velocity must be 'zero'")
    if rec.at_rest_initially:
        return V.copy(), np.zeros((n, 3))
    if rec.num_markers == 0 and not rec.has_drive:
        raise ValueError(
            "initial_state: the recording has no markers or drive points and is not at rest "
            "initially; track its clouds into markers first (`matlearn track SCENE --out DIR`, which "
            "writes a scene whose recordings have them)"
        )
    emb = embedding if embedding is not None else embed_points(scene.mesh, rec.marker_rest)
    integ = scene.integrator(model)
    if not rec.seen[0].any() and not rec.has_drive:
        raise ValueError("initial_state: no marker is seen in frame 0, and the recording does not say it "
                         "starts at rest (at_rest_initially), so its first pose is unknown")
    x0 = _held_pose(scene, model, rec, 0, emb, integ, refine)
    if start == "released":
        from .release import released_start

        return released_start(scene, model, rec, emb, x0), np.zeros((n, 3))
    if velocity == "zero" or rec.num_frames < 2:
        return x0, np.zeros((n, 3))
    x1 = _held_pose(scene, model, rec, 1, emb, integ, refine)
    return x0, (x1 - x0) / (rec.times[1] - rec.times[0])


# ---------------------------------------------------------------------------- simulation
def follow_targets(scene, model, idx: np.ndarray, targets: np.ndarray, x0: np.ndarray, v0: np.ndarray,
                   max_newton: int = 8, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """(X, Vel), each (S+1, n, 3): the scene's constrained run from (x0, v0) whose vertices `idx`
    follow `targets` (S+1, k, 3) at the simulation steps (one C++ call). Where every free vertex
    is prescribed (a body one tet across with a marker near every vertex) there is nothing to
    solve: the run is the targets, its velocities backward differences."""
    V = np.asarray(scene.mesh.vertices, float)
    if len(np.union1d(idx, scene.fixed)) == len(V):
        X = np.repeat(V[None], len(targets), axis=0)
        X[:, idx] = targets
        Vel = np.zeros_like(X)
        Vel[0] = v0
        Vel[1:] = np.diff(X, axis=0) / scene.time_step
        return X, Vel
    integ = scene.integrator(model, max_newton=max_newton)
    integ.set_prescribed(idx)
    integ.set_state(x0, v0)
    return integ.simulate_constrained(np.ascontiguousarray(targets[1:]), np.zeros_like(V), progress=progress)


# A span that ends less than this fraction of a step past a whole number of steps is that number
# of steps: times stored as float32 (resolution ~6e-8 of their value) end a hair past the step
# they mean (0.3 s at 1 ms steps read as 0.30000001 s was simulated to 0.301 s), and the last
# frame is then read at the last step, off by at most this fraction of a step's motion.
STEP_ROUNDING = 1e-3


def steps_covering(span: float, h: float) -> int:
    """The number of steps of length h that cover `span` (s), up to STEP_ROUNDING."""
    return int(np.ceil(span / h - STEP_ROUNDING))


def simulation_times(scene, rec: Recording) -> np.ndarray:
    """Step times covering the recording: times[0] + h * (0..S), S = steps_covering(span, h)."""
    h = scene.time_step
    steps = steps_covering(rec.times[-1] - rec.times[0], h)
    return rec.times[0] + h * np.arange(steps + 1)


def drive_schedule(scene, rec: Recording, sim_t, x0):
    """(driven vertices (k,), x0 with them at their frame-0 target, their targets at the end of
    each step (S, k, 3)) of `rec` simulated at times sim_t (S+1,) from positions x0; without drive
    points: ((0,), x0 unchanged, None)."""
    didx, dtargets = drive_vertices(scene, rec)
    if not len(didx):
        return didx, x0, None
    x0 = np.array(x0, float)
    x0[didx] = interpolate_frames(rec.times, dtargets, sim_t[:1])[0]
    return didx, x0, np.ascontiguousarray(interpolate_frames(rec.times, dtargets, sim_t[1:]))


def simulate_recording(scene, model, rec: Recording, progress=None, state=None,
                       f_ext=None, max_newton: int = 8, chunk: int | None = None, after_chunk=None,
                       steps: int | None = None):
    """Simulate over the recording's span at scene.time_step from `state` = (x0, v0) (default:
    :func:`initial_state`), honouring clamped and driven vertices, in one C++ call. Returns
    (sim_times (S+1,), X (S+1, n, 3), V (S+1, n, 3)). progress(done, total) is called from C++
    every few steps. after_chunk(steps_done, X_new): the simulation runs `chunk` steps per C++
    call and hands over each call's new frames (it may raise to stop the simulation early: a
    bounded check); the trajectory is bitwise the one of a single call. steps: simulate only the
    first `steps` steps (default: the whole span)."""
    n = scene.mesh.num_vertices
    x0, v0 = state if state is not None else initial_state(scene, model, rec)
    f = np.zeros((n, 3)) if f_ext is None else np.asarray(f_ext, float)
    sim_t = simulation_times(scene, rec)
    if steps is not None:
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        sim_t = sim_t[:steps + 1]
    steps = len(sim_t) - 1
    integ = scene.integrator(model, max_newton=max_newton)
    didx, x0, targets = drive_schedule(scene, rec, sim_t, x0)
    if len(didx):
        integ.set_prescribed(didx)
    integ.set_state(x0, v0)

    def run(k, s):  # k steps from step s
        if len(didx):
            return integ.simulate_constrained(np.ascontiguousarray(targets[s:s + k]), f, progress=progress)
        return integ.simulate(k, f, 1, progress=progress)

    if after_chunk is None:
        X, Vel = run(steps, 0)
    else:
        Xs, Vs, s = [], [], 0
        while s < steps:
            k = min(max(1, int(chunk or steps)), steps - s)
            X, Vel = run(k, s)
            first = 0 if s == 0 else 1  # every call repeats its start frame
            Xs.append(X[first:])
            Vs.append(Vel[first:])
            s += k
            after_chunk(s, Xs[-1])
        X, Vel = np.concatenate(Xs), np.concatenate(Vs)
    warn_unconverged(integ, "simulate_recording")
    return sim_t, X, Vel


def predict_markers(scene, model, rec: Recording, sim=None, embedding: Embedding | None = None,
                    progress=None) -> np.ndarray:
    """Model-predicted marker positions (T, K, 3) at rec.times: the simulated trajectory
    (default :func:`simulate_recording`) through the markers' embedding, linear in time between
    steps."""
    emb = embedding if embedding is not None else embed_points(scene.mesh, rec.marker_rest)
    sim_t, X, _ = sim if sim is not None else simulate_recording(scene, model, rec, progress)
    if rec.num_frames < len(sim_t):  # both maps are linear: apply the cheaper one first
        return emb.apply(interpolate_frames(sim_t, X, rec.times))
    return interpolate_frames(sim_t, emb.apply(X), rec.times)


def trajectory_error(pred: np.ndarray, rec, object_size: float) -> dict:
    """Max and RMS marker error over seen markers and frames, in % of object_size.
    rec: a Recording or an observed marker array (T, K, 3) with NaN = unseen."""
    obs = rec.markers if isinstance(rec, Recording) else np.asarray(rec, float)
    pred = np.asarray(pred, float)
    if pred.shape != obs.shape:
        raise ValueError(f"pred: expected shape {obs.shape} like the observed markers, got {pred.shape}")
    if not object_size > 0:
        raise ValueError(f"object_size must be > 0, got {object_size}")
    seen = ~np.isnan(obs).any(axis=2)
    err = np.linalg.norm(pred - obs, axis=2)[seen]
    if len(err) == 0:
        raise ValueError("trajectory_error: no seen marker to compare")
    if not np.all(np.isfinite(err)):
        raise ValueError("trajectory_error: prediction contains NaN/Inf at seen markers")
    return {
        "max_error_pct": float(100.0 * err.max() / object_size),
        "rms_error_pct": float(100.0 * np.sqrt(np.mean(err**2)) / object_size),
        "samples": int(len(err)),
    }


def combine_errors(errors: list[dict]) -> dict:
    """Pool per-recording errors: max of maxima, RMS over all samples."""
    if not errors:
        raise ValueError("combine_errors: no errors to combine")
    n = sum(e["samples"] for e in errors)
    ms = sum(e["samples"] * e["rms_error_pct"] ** 2 for e in errors) / n
    return {
        "max_error_pct": max(e["max_error_pct"] for e in errors),
        "rms_error_pct": float(np.sqrt(ms)),
        "samples": n,
    }


def score_recording(scene, model, rec: Recording, start: str = SCORE_START, progress=None) -> dict:
    """The error dict (:func:`trajectory_error`) of one recording replayed with `model` from the
    initial state `start`."""
    emb = embed_points(scene.mesh, rec.marker_rest)
    state = initial_state(scene, model, rec, emb, start=start)
    sim = simulate_recording(scene, model, rec, progress, state=state)
    return trajectory_error(predict_markers(scene, model, rec, sim=sim, embedding=emb), rec, scene.object_size)


def score(scene, model=None, role: str = "test", progress=None, start: str = SCORE_START) -> dict:
    """Replay every recording of `role` with `model` (default: the scene's nominal model) from
    the initial state `start` (:func:`initial_state`; default SCORE_START, the protocol every
    model is scored with) and return {"recordings": [per-recording error dict], **pooled error}."""
    model = model if model is not None else scene.model()
    recs = [rec for rec in scene.recordings_with_role(role) if rec.num_markers > 0]
    if progress is None:  # the recordings on the cores (matlearn.parallel; the same result)
        per = pmap(lambda rec: score_recording(scene, model, rec, start), recs)
    else:  # one progress display, one recording at a time
        per = [score_recording(scene, model, rec, start, progress) for rec in recs]
    if not per:
        raise ValueError(f"score: the scene has no '{role}' recording with markers")
    return {"recordings": per, **combine_errors(per)}
