"""Initial trajectory for the space-time step (method.md section 4): a constrained forward
simulation in which the vertices nearest the observed markers follow the markers.

Markers are interpolated linearly to the simulation steps. A marker unseen in some frames (NaN)
takes, in each such frame, the displacement that the markers seen in that frame interpolate at
its rest position (a thin-plate spline over rest positions, `spatial_fill`), except across short
gaps inside its seen span (at most SHORT_GAP frames), which are interpolated in time; markers
never seen are ignored. Several markers sharing a nearest vertex prescribe the
average of their displacements. Clamped vertices stay clamped, driven vertices follow the drive
(the drive wins over a marker).
"""
from __future__ import annotations

import numpy as np

from ..embedding import embed_points
from ..replay import drive_vertices, follow_targets, interpolate_frames, simulation_times


# gaps inside a marker's seen span up to this many frames are interpolated in time, longer ones
# (and the frames before its first / after its last sighting) from the other markers of the frame
SHORT_GAP = 2


def fill_marker_gaps(times: np.ndarray, markers: np.ndarray, rest: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Markers (T, K, 3) with their NaN gaps filled. Returns (filled (T, K', 3), kept marker
    indices (K',)) where markers never seen are dropped.

    Without `rest` every gap is interpolated linearly in time and held constant before the first
    / after the last sighting. With the markers' rest positions `rest` (K, 3), a frame's unseen
    marker takes instead the displacement the frame's seen markers interpolate at its rest
    position (`spatial_fill`), except across gaps of at most SHORT_GAP frames inside its seen span.
    Holding a marker where it was first seen made the initial trajectory pull it there in every
    earlier frame: a falling bar seen through one-sided scans (25-51 of its 198 surface vertices
    per frame, none in every frame; exact positions) then barely learned in an iteration (train
    error 4.78 -> 4.66 %), where these fills give 1.86 %."""
    seen = ~np.isnan(markers).any(axis=2)
    keep = np.flatnonzero(seen.any(axis=0))
    out = np.empty((len(times), len(keep), 3))
    for j, k in enumerate(keep):  # loop over markers (not frames); np.interp is vectorised
        s = seen[:, k]
        for d in range(3):
            out[:, j, d] = np.interp(times, times[s], markers[s, k, d])
    if rest is None:
        return out, keep
    s = seen[:, keep]
    T = len(times)
    first = np.argmax(s, axis=0)
    last = T - 1 - np.argmax(s[::-1], axis=0)
    # the length of the unseen run each sample lies in: the unseen samples of a marker after the
    # same number of sightings form one run
    key = np.cumsum(s, axis=0) * s.shape[1] + np.arange(s.shape[1])
    run = np.bincount(key[~s], minlength=key.max() + 1)[key]
    frame = np.arange(T)[:, None]
    inside = (frame > first[None]) & (frame < last[None])
    spatial = ~s & ~(inside & (run <= SHORT_GAP))
    R = np.asarray(rest, float)[keep]
    for t in np.flatnonzero(spatial.any(axis=1)):  # only frames with such gaps
        got = spatial_fill(R[s[t]], markers[t, keep[s[t]]] - R[s[t]], R[spatial[t]])
        if got is not None:
            out[t, spatial[t]] = R[spatial[t]] + got
    return out, keep


def spatial_fill(rest_seen: np.ndarray, disp_seen: np.ndarray, rest_wanted: np.ndarray):
    """Displacements (M, 3) at `rest_wanted` interpolated from those of the seen markers: a
    thin-plate spline with an affine part (scipy's RBFInterpolator), exact at the seen markers;
    None where the seen markers cannot carry it (fewer than 4, or all in one plane)."""
    from scipy.interpolate import RBFInterpolator

    if len(rest_seen) < 4:
        return None
    c = rest_seen - rest_seen.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[-1] <= 1e-3 * max(sv[0], 1e-300):  # (nearly) coplanar: the affine part is not determined
        return None
    try:
        return RBFInterpolator(rest_seen, disp_seen, kernel="thin_plate_spline", degree=1)(rest_wanted)
    except (np.linalg.LinAlgError, ValueError):
        return None


def initial_trajectory(scene, model, rec, embedding=None, progress=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Constrained forward simulation following the markers of `rec`.
    Returns (sim_times (S+1,), X (S+1, n, 3), prescribed vertex indices)."""
    if rec.num_markers == 0:
        raise ValueError("initial_trajectory: the recording has no markers (track its clouds first)")
    emb = embedding if embedding is not None else embed_points(scene.mesh, rec.marker_rest)
    V = np.asarray(scene.mesh.vertices, float)
    n = len(V)
    sim_t = simulation_times(scene, rec)
    filled, keep = fill_marker_gaps(rec.times, rec.markers, rec.marker_rest)
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
