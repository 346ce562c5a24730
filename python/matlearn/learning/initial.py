"""Initial trajectory for the space-time step (method.md section 4): a constrained forward
simulation in which the vertices nearest the observed markers follow the markers.

Markers are interpolated linearly to the simulation steps. Partially observed markers (NaN in
some frames) are interpolated across their gaps and held before their first / after their last
sighting; markers never seen are ignored. Several markers sharing a nearest vertex prescribe the
average of their displacements. Clamped vertices stay clamped, driven vertices follow the drive
(the drive wins over a marker).
"""
from __future__ import annotations

import numpy as np

from ..embedding import embed_points
from ..replay import drive_vertices, follow_targets, interpolate_frames, simulation_times


def fill_marker_gaps(times: np.ndarray, markers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Markers (T, K, 3) with NaN gaps filled by linear interpolation in time (held constant
    outside the seen span). Returns (filled (T, K', 3), kept marker indices (K',)) where markers
    never seen are dropped."""
    seen = ~np.isnan(markers).any(axis=2)
    keep = np.flatnonzero(seen.any(axis=0))
    out = np.empty((len(times), len(keep), 3))
    for j, k in enumerate(keep):  # loop over markers (not frames); np.interp is vectorised
        s = seen[:, k]
        for d in range(3):
            out[:, j, d] = np.interp(times, times[s], markers[s, k, d])
    return out, keep


def initial_trajectory(scene, model, rec, embedding=None, progress=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Constrained forward simulation following the markers of `rec`.
    Returns (sim_times (S+1,), X (S+1, n, 3), prescribed vertex indices)."""
    if rec.num_markers == 0:
        raise ValueError("initial_trajectory: the recording has no markers (track its clouds first)")
    emb = embedding if embedding is not None else embed_points(scene.mesh, rec.marker_rest)
    V = np.asarray(scene.mesh.vertices, float)
    n = len(V)
    sim_t = simulation_times(scene, rec)
    filled, keep = fill_marker_gaps(rec.times, rec.markers)
    near = emb.nearest_vertices()[keep]
    disp = filled - rec.marker_rest[keep][None]  # (T, K', 3)
    uniq, inv = np.unique(near, return_inverse=True)
    vdisp = np.zeros((len(rec.times), len(uniq), 3))
    np.add.at(vdisp, (slice(None), inv), disp)
    vdisp /= np.bincount(inv, minlength=len(uniq))[None, :, None]
    targets = V[uniq][None] + vdisp  # (T, U, 3) at recording times
    didx, dtargets = drive_vertices(scene, rec)
    mask = ~np.isin(uniq, np.union1d(np.asarray(scene.fixed), didx))
    uniq, targets = uniq[mask], targets[:, mask]
    idx = np.concatenate([uniq, didx]).astype(np.int64)
    if len(idx) == 0:
        raise ValueError("initial_trajectory: every marker's nearest mesh vertex is clamped, so no free "
                         "vertex can follow the markers; are the markers on the moving part of the body "
                         "and in the mesh's units (m)?")
    tpos = np.concatenate([targets, dtargets], axis=1)
    steps_t = interpolate_frames(rec.times, tpos, sim_t)  # (S+1, k, 3)
    from .loop import robust_initial_state

    x0, v0 = robust_initial_state(scene, model, rec, emb)
    x0 = np.array(x0, float)
    x0[idx] = steps_t[0]
    X, _ = follow_targets(scene, model, idx, steps_t, x0, np.zeros((n, 3)), progress=progress)
    return sim_t, X, idx
