"""Python side of the sparse reduced space-time optimisation (method.md section 5).

`build_problem` turns a scene, a model, a recording and a basis into the C++
`_core.spacetime.SpaceTimeProblem`: frames at the simulation step over the recording span, the
marker embedding as a selection operator S (markers need not sit on vertices), samples at the
recording times interpolated between their neighbouring frames (recordings need not be at the
simulation rate), clamped and driven vertices in x_base. `solve_spacetime` runs Gauss-Newton
(each step CGLS on J products computed in C++) and returns positions, velocities and the control
forces ("gentle forces") of every frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .. import _core
from ..embedding import embed_points
from ..replay import drive_vertices, interpolate_frames, simulation_times


@dataclass
class SpaceTimeSetup:
    """problem: the C++ problem; phi (3n, r); base (frames, n, 3) constrained-vertex positions
    (rest elsewhere); times (frames,) simulation times; constrained: clamped + driven vertices."""

    problem: object
    phi: np.ndarray
    base: np.ndarray
    times: np.ndarray
    constrained: np.ndarray

    def project(self, X: np.ndarray) -> np.ndarray:
        """Least-squares modal coordinates Z (frames, r) of positions X (frames, n, 3)."""
        D = (np.asarray(X, float) - self.base).reshape(len(X), -1)
        return D @ self.phi  # phi has orthonormal columns

    def positions(self, Z) -> np.ndarray:
        return self.problem.positions(np.ascontiguousarray(Z))


def constrained_vertices(scene, rec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(constrained (c,), driven (k,), drive targets at the simulation steps (frames, k, 3))."""
    didx, dtargets = drive_vertices(scene, rec)
    sim_t = simulation_times(scene, rec)
    dsteps = interpolate_frames(rec.times, dtargets, sim_t) if len(didx) else np.zeros((len(sim_t), 0, 3))
    constrained = np.union1d(np.asarray(scene.fixed, np.int64), didx).astype(np.int64)
    return constrained, didx, dsteps


def observation_weight(model, time_step: float, lam: float) -> float:
    """The C++ weight of the observation rows for the user's dimensionless `lam`:
    lam * (mean vertex mass) / h^2 (N/m). With lam = 1 a marker error of 1 m weighs like the
    inertial force of an average vertex displaced by 1 m within one step, which keeps the
    balance between physics and observations independent of the object's size, density, mesh
    resolution and time step (lam from ~0.01 to ~1e5 converge; see tests/bench)."""
    if not lam > 0:
        raise ValueError(f"lambda must be > 0, got {lam}")
    return float(lam * np.mean(np.asarray(model.vertex_mass)) / time_step**2)


def build_problem(scene, model, rec, phi, lam: float, embedding=None,
                  nominal_tangent: bool = True) -> SpaceTimeSetup:
    """Space-time problem for one recording. phi (3n, r) must be zero on constrained rows;
    lam is dimensionless (:func:`observation_weight`)."""
    mesh = scene.mesh
    n = mesh.num_vertices
    V = np.asarray(mesh.vertices, float)
    constrained, didx, dsteps = constrained_vertices(scene, rec)
    phi = np.asarray(phi, float)
    if phi.shape[0] != 3 * n:
        raise ValueError(f"phi: expected shape (3*{n}, r), got {phi.shape}")
    sim_t = simulation_times(scene, rec)
    frames = len(sim_t)
    base = np.repeat(V[None], frames, axis=0)
    if len(didx):
        base[:, didx] = dsteps
    mass = np.asarray(model.vertex_mass)
    fext = mass[:, None] * np.asarray(scene.gravity)[None, :]
    # Observations: markers through their embedding, samples interpolated between frames.
    emb = embedding if embedding is not None else embed_points(mesh, rec.marker_rest)
    K = emb.num_points
    E = emb.matrix(n)
    S = sp.kron(E, sp.eye(3), format="csr")  # (3K, 3n)
    S_phi = np.ascontiguousarray(S @ phi)
    S_base = np.ascontiguousarray((S @ base.reshape(frames, -1).T).T)
    h = scene.time_step
    inside = (rec.times >= sim_t[0] - 1e-12) & (rec.times <= sim_t[-1] + 1e-12)
    t = rec.times[inside]
    frame = np.clip(np.floor((t - sim_t[0]) / h + 1e-9).astype(np.int64), 0, frames - 2)
    weight = np.clip((t - sim_t[frame]) / h, 0.0, 1.0)
    targets = np.ascontiguousarray(rec.markers[inside].reshape(len(t), 3 * K))
    prob = _core.spacetime.SpaceTimeProblem(
        model, phi, base, fext, h, S_phi, S_base, frame, weight, targets, observation_weight(model, h, lam), nominal_tangent
    )
    return SpaceTimeSetup(prob, phi, base, sim_t, constrained)


def solve_spacetime(setup: SpaceTimeSetup, X0, iterations: int = 8, cg_iterations: int = 400,
                    cg_tolerance: float = 1e-8, tolerance: float = 2e-3, solver: str | None = None,
                    progress=None, jacobian_every: int = 1) -> dict:
    """Gauss-Newton from the trajectory X0 (frames, n, 3). Returns dict(Z, X (frames, n, 3),
    V (frames, n, 3), control_forces (frames-2, n, 3) for frames 2..N, report).
    solver: "lm" (the default, None, unless jacobian_every > 1: Levenberg-Marquardt, the damped normal equations (J^T J + mu
    diag(J^T J)) dz = -J^T C factorised at every trial, mu adapted from the gain ratio), "pcgls"
    (CG on the normal equations preconditioned by a frozen factorisation; continued with CGLS
    when it stalls), "cgls" (Jacobi-scaled CGLS on J, matrix-free) or "direct". Why LM (session
    22, docs/results.md "Session 22"): with sparse markers J is ill-conditioned and the undamped
    factorised steps are dominated by round-off in the directions the markers barely determine:
    on the StVK bar of bench/learning_table.py (6 % markers) numpy's BLAS thread count decided
    which of two learning paths pcgls took (held-out 0.16 / 0.15 or 0.13 / 0.27 %); with LM one
    and two threads give the same run (0.13 / 0.32 %). CGLS, capped at cg_iterations, is an
    unconverged inner solve (it fails the exact-model recovery at lambda 0.01 that LM and pcgls
    pass; 6k-tet bar of bench/learning_scale.py: train 0.155 % after 4 iterations vs 0.100 % LM,
    0.041 % pcgls). With "lm" the report's cg_iterations counts the damping trials of each step
    and step_length is 1 for an accepted step.
    jacobian_every k > 1: the Jacobian blocks are re-evaluated only at every k-th step and after
    a shortened step (chord Gauss-Newton; the residual stays exact); a line-search variant, so
    with k > 1 the default solver is pcgls (an explicit "lm" is refused by the core)."""
    if solver is None:
        solver = "lm" if jacobian_every == 1 else "pcgls"
    Z0 = np.ascontiguousarray(setup.project(X0))
    rep = setup.problem.solve(Z0, iterations, cg_iterations, cg_tolerance, tolerance, solver, progress,
                              jacobian_every)
    Z = rep.pop("Z")
    steps = list(rep["step_length"])
    # A stall: a step shortened below 1/4, or the solve stopped before its budget with its last
    # step shortened (a small decrease after a shortened step is a poor direction, not
    # convergence). The second was missing before: measured on the StVK bar of
    # bench/learning_table.py, iteration 8, steps (1/2, 1/4) took the cost 0.0403 -> 0.0331 and
    # stopped there, while steps (1/2, 1/8, ...) went on with CGLS to 0.0186; which of the two
    # happened was decided by round-off (numpy's BLAS thread count), and so was the learning run.
    stalled = bool(steps) and (min(steps) < 0.25 or (len(steps) < iterations and steps[-1] < 1.0))
    if solver in ("pcgls", "direct") and stalled:
        # The factorised normal equations J^T J square the condition number of J. With sparse
        # observations (a few markers) they are so ill-conditioned that the factorised step
        # is wrong and the line search stalls (measured on a bar with 5 markers: cost
        # 27.4 -> 26.9, step 1/16, then no descent; Jacobi-scaled CGLS on J itself: 27.4 ->
        # 1.12 with full steps). Continue with CGLS from where the solve stalled.
        more = setup.problem.solve(np.ascontiguousarray(Z), max(1, iterations - len(steps) + 1),
                                   cg_iterations, cg_tolerance, tolerance, "cgls", progress,
                                   jacobian_every)
        Z = more.pop("Z")
        for key in ("cost", "physics_cost"):
            rep[key] = list(rep[key]) + list(more[key])[1:]
        for key in ("cg_iterations", "step_length"):
            rep[key] = list(rep[key]) + list(more[key])
        rep["fallback"] = "cgls"
    X = setup.problem.positions(Z)
    h = setup.times[1] - setup.times[0]
    Vel = np.zeros_like(X)
    Vel[1:] = (X[1:] - X[:-1]) / h
    fc = setup.problem.control_forces(Z)
    return {"Z": Z, "X": X, "V": Vel, "control_forces": fc, "report": rep}
