"""The released start: the initial pose of a recording that starts from a held, deformed pose,
estimated from its markers better than the held pose of :mod:`replay` does.

The held pose (replay._held_pose) prescribes the vertices nearest the frame-0 markers: the body
is held by point forces at the markers. A real body is held elsewhere (a hand, a load, a
support), so with sparse markers the held pose is kinked at the markers and wrong between and
beyond them, and the released motion starts wrong. The released start replaces it in three
steps, using only the recording and the model:

1. *Smooth holds*: static equilibria under smooth hold forces f = M Phi c, Phi the r lowest
   vibration modes (mass-normalised) of the model at the held pose on the free, undriven DOFs,
   with c fitted to the frame-0 markers by Gauss-Newton (line search) with a minimum-energy
   regulariser (c = Lambda^(1/2) z, |z|^2 = twice the energy of the modes' linear response); one
   candidate per r in MODE_COUNTS. Few modes give a smooth pose that may miss markers, many modes
   approach the held pose.
2. *Choice by the release*: every candidate, and the held pose itself, is released (zero
   velocity) and simulated over the first frames of the recording, those at times
   <= t0 + T1 / WINDOW_DIVISOR (T1: the lowest period of the model at the held pose; at least
   MIN_WINDOW_FRAMES frames); the candidate with the lowest marker rms over them is kept.
3. *Window refinement*: one Gauss-Newton step x0 += Phi_w dc over the REFINE_MODES lowest modes
   on the marker misfit over the same frames (Jacobian by finite differences of released
   simulations), kept only if it lowers that misfit.

Only the start's frames (step 2-3) inform the start; the scoring still compares every frame.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sl
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .parallel import pmap

MODE_COUNTS = (6, 12, 24, 48)
REFINE_MODES = 12
WINDOW_DIVISOR = 8.0
MIN_WINDOW_FRAMES = 3
_DENSE_EIG_DOFS = 1500  # dense eigensolver below this many free DOFs, shift-invert Lanczos above


def _free_dofs(scene, rec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(driven vertices (D,), their targets (frames, D, 3), free undriven DOFs (3m,)) of the
    recording on the scene (replay.drive_vertices)."""
    from .replay import drive_vertices

    didx, targets = drive_vertices(scene, rec)
    n = scene.mesh.num_vertices
    keep = np.setdiff1d(np.arange(n), np.union1d(np.asarray(scene.fixed), didx))
    return didx, targets, (3 * keep[:, None] + np.arange(3)).ravel()


def vibration_modes(model, x: np.ndarray, dofs: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """The r lowest eigenpairs (lam (r,), Phi (len(dofs), r)) of K Phi = M Phi diag(lam) at
    positions x (n, 3), K the PSD-projected stiffness restricted to `dofs` (the others held),
    Phi^T M Phi = I."""
    n = len(x)
    K = model.stiffness(x, np.zeros((n, 3)), project_psd=True).tocsr()[dofs][:, dofs]
    m = np.repeat(np.asarray(model.vertex_mass, float), 3)[dofs]
    r = int(min(r, len(dofs)))
    if r < 1:
        raise ValueError("vibration_modes: no free DOF")
    if len(dofs) <= _DENSE_EIG_DOFS:
        lam, Phi = sl.eigh(K.toarray(), np.diag(m), subset_by_index=[0, r - 1])
    else:
        shift = -1e-6 * float(K.diagonal().mean() / m.mean())
        lam, Phi = sla.eigsh(K.tocsc(), k=r, M=sp.diags(m).tocsc(), sigma=shift, which="LM")
        order = np.argsort(lam)
        lam, Phi = lam[order], Phi[:, order]
    return np.maximum(lam, 1e-12 * max(lam.max(), 1e-300)), Phi


def window_frames(scene, rec, lowest_eigenvalue: float) -> int:
    """Number of recording frames in the release window: times <= t0 + T1 / WINDOW_DIVISOR,
    T1 = 2 pi / sqrt(lowest_eigenvalue), at least MIN_WINDOW_FRAMES (or all frames)."""
    t1 = 2.0 * np.pi / np.sqrt(lowest_eigenvalue)
    k = int(np.searchsorted(rec.times, rec.times[0] + t1 / WINDOW_DIVISOR, side="right"))
    return int(min(rec.num_frames, max(MIN_WINDOW_FRAMES, k)))


class _Window:
    """Released simulations of one recording over its first `frames` frames."""

    def __init__(self, scene, model, rec, emb, frames: int):
        from .replay import simulation_times, steps_covering

        self.scene, self.model, self.rec, self.emb = scene, model, rec, emb
        self.frames = frames
        self.steps = steps_covering(rec.times[frames - 1] - rec.times[0], scene.time_step)
        self.steps = max(1, min(self.steps, len(simulation_times(scene, rec)) - 1))
        self.seen = rec.seen[:frames]
        self.obs = rec.markers[:frames][self.seen]

    def residual(self, x0: np.ndarray) -> np.ndarray:
        """Marker misfit (predicted - observed) over the window's seen samples, flattened."""
        from .replay import interpolate_frames, simulate_recording

        n = len(x0)
        sim_t, X, _ = simulate_recording(self.scene, self.model, self.rec, state=(x0, np.zeros((n, 3))),
                                         steps=self.steps)
        P = interpolate_frames(sim_t, self.emb.apply(X), self.rec.times[:self.frames])
        return (P[self.seen] - self.obs).ravel()

    def rms(self, x0: np.ndarray) -> float:
        try:
            d = self.residual(x0)
        except RuntimeError:
            return np.inf
        return float(np.sqrt(np.mean(d**2))) if np.all(np.isfinite(d)) else np.inf


def smooth_hold(scene, model, rec, emb, x_held: np.ndarray, lam: np.ndarray, Phi: np.ndarray,
                dofs: np.ndarray, integ, iterations: int = 6, frame: int = 0) -> np.ndarray:
    """Static equilibrium under hold forces M Phi c fitted to the markers of `frame` (step 1 of
    the module docstring), started from the held pose's reactions projected onto the modes.
    `integ` has the scene's clamp and the drive vertices prescribed at `x_held`'s positions.
    Raises RuntimeError when a static solve fails."""
    n = len(x_held)
    seen = rec.seen[frame]
    C = sp.kron(emb.matrix(n)[seen], sp.eye(3)).tocsr()[:, dofs]
    obs = rec.markers[frame, seen].ravel()
    mass = np.repeat(np.asarray(model.vertex_mass, float), 3)
    g = np.tile(np.asarray(scene.gravity, float), n)
    react = -(np.asarray(model.forces(x_held, np.zeros((n, 3))), float).ravel() + mass * g)
    c = Phi.T @ react[dofs]
    MPhi = mass[dofs][:, None] * Phi
    sq = np.sqrt(lam)

    def solve(c, x_from):
        f = np.zeros(3 * n)
        f[dofs] = MPhi @ c
        integ.set_state(x_from, np.zeros((n, 3)))
        integ.static_solve(f.reshape(n, 3), load_steps=1)
        x = np.array(integ.x)
        return x, obs - C @ x.ravel()[dofs]

    x, res = solve(c, x_held)
    for _ in range(iterations):
        K = model.stiffness(x, np.zeros((n, 3)), project_psd=True).tocsr()[dofs][:, dofs].tocsc()
        Jz = C @ sla.splu(K).solve(MPhi * sq[None])  # d markers / dz, c = sqrt(lam) z
        z = c / sq
        A = Jz.T @ Jz
        rho = 1e-6 * np.trace(A) / len(z)
        dz = np.linalg.solve(A + rho * np.eye(len(z)), Jz.T @ res - rho * z)
        for t in (1.0, 0.5, 0.25):
            try:
                xt, rt = solve(c + t * sq * dz, x)
            except RuntimeError:
                continue
            if rt @ rt < res @ res:
                break
        else:
            break
        gain = 1.0 - np.sqrt((rt @ rt) / max(res @ res, 1e-300))
        c, x, res = c + t * sq * dz, xt, rt
        if gain < 1e-2:
            break
    return x


def refine_in_window(window: _Window, x0: np.ndarray, Phi: np.ndarray, dofs: np.ndarray,
                     size: float) -> np.ndarray:
    """One Gauss-Newton step x0 + Phi dc on the window misfit (finite-difference Jacobian), kept
    only if it lowers the misfit (step 3 of the module docstring)."""
    n = len(x0)
    r0 = window.residual(x0)

    def column(j):  # the columns' released simulations run on the cores (parallel.pmap)
        eps = 1e-4 * size / max(np.abs(Phi[:, j]).max(), 1e-300)
        xj = x0.copy().ravel()
        xj[dofs] += eps * Phi[:, j]
        return (window.residual(xj.reshape(n, 3)) - r0) / eps

    J = np.stack(pmap(column, range(Phi.shape[1])), axis=1)
    A = J.T @ J
    dc = -np.linalg.solve(A + 1e-8 * np.trace(A) / len(A) * np.eye(len(A)), J.T @ r0)
    x1 = x0.copy().ravel()
    x1[dofs] += Phi @ dc
    x1 = x1.reshape(n, 3)
    return x1 if window.rms(x1) < np.sqrt(np.mean(r0**2)) else x0


def released_start(scene, model, rec, emb, x_held: np.ndarray,
                   mode_counts=MODE_COUNTS, refine_modes: int = REFINE_MODES) -> np.ndarray:
    """The released start x0 (n, 3) of `rec` (velocity zero) from its held pose `x_held`; see the
    module docstring. The candidates and the refinement's Jacobian columns are independent
    simulations and run on the cores (matlearn.parallel; the same result on one thread)."""
    x_held = np.asarray(x_held, float)
    didx, dtargets, dofs = _free_dofs(scene, rec)
    if len(dofs) == 0:
        return x_held.copy()
    rmax = int(min(max(max(mode_counts, default=0), refine_modes), len(dofs)))
    lam, Phi = vibration_modes(model, x_held, dofs, rmax)
    window = _Window(scene, model, rec, emb, window_frames(scene, rec, lam[0]))

    def candidate(r):  # its own integrator (each static solve starts afresh: the same poses)
        integ = scene.integrator(model)
        integ.set_prescribed(didx if len(didx) else np.zeros(0, np.int64))
        try:
            x = smooth_hold(scene, model, rec, emb, x_held, lam[:r], Phi[:, :r], dofs, integ)
        except RuntimeError:
            return None
        return x, window.rms(x)

    best, best_rms = x_held, window.rms(x_held)
    for got in pmap(candidate, sorted({int(min(r, len(dofs))) for r in mode_counts})):
        if got is not None and got[1] < best_rms:
            best, best_rms = got
    if refine_modes > 0 and np.isfinite(best_rms):
        try:
            best = refine_in_window(window, best, Phi[:, :refine_modes], dofs, scene.object_size)
        except RuntimeError:
            pass
    if len(didx):
        best = best.copy()
        best[didx] = dtargets[0]
    return best
