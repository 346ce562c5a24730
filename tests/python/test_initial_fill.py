"""Gaps in marker tracks (learning/initial.py): the initial trajectory's markers are filled in
time across short gaps and from the frame's other markers elsewhere (a thin-plate spline over rest
positions), never held where a marker was first or last seen."""
import numpy as np

from matlearn.learning.initial import SHORT_GAP, fill_marker_gaps, initial_trajectory
from matlearn.recording import Recording
from matlearn.scene import load_scene

from learning_cases import small_bar_case


def _affine_tracks(T=12, K=30, seed=0):
    """Markers moved by an affine field whose coefficients change non-linearly in time (so time
    interpolation is not exact, while the spline, affine part included, is)."""
    rng = np.random.default_rng(seed)
    rest = rng.uniform(-0.05, 0.05, size=(K, 3))
    t = 0.01 * np.arange(T)
    A = 0.2 * np.sin(40 * t)[:, None, None] * rng.normal(size=(3, 3))[None]
    b = 0.01 * np.cos(30 * t)[:, None] * rng.normal(size=3)[None]
    truth = rest[None] + np.einsum("tij,kj->tki", A, rest) + b[:, None]
    return t, rest, truth


def test_without_rest_positions_gaps_are_interpolated_in_time_and_held_outside():
    t, rest, truth = _affine_tracks()
    m = truth.copy()
    m[:4, 0] = np.nan  # first seen at frame 4
    m[6, 1] = np.nan  # one frame missing
    out, keep = fill_marker_gaps(t, m)
    np.testing.assert_array_equal(keep, np.arange(len(rest)))
    np.testing.assert_array_equal(out[:4, 0], np.repeat(truth[4:5, 0], 4, axis=0))
    np.testing.assert_allclose(out[6, 1], 0.5 * (truth[5, 1] + truth[7, 1]))


def test_long_and_outer_gaps_come_from_the_frames_other_markers():
    t, rest, truth = _affine_tracks()
    m = truth.copy()
    m[:4, 0] = np.nan  # before the first sighting: spatial
    m[3:9, 1] = np.nan  # a long inner gap: spatial
    m[6, 2] = np.nan  # a short inner gap (1 frame <= SHORT_GAP): in time
    m[10:, 3] = np.nan  # after the last sighting: spatial
    m[:, 4] = np.nan  # never seen: dropped
    out, keep = fill_marker_gaps(t, m, rest)
    assert 4 not in keep and len(keep) == len(rest) - 1
    got = dict(zip(keep, range(len(keep))))
    np.testing.assert_allclose(out[:4, got[0]], truth[:4, 0], atol=1e-10)  # an affine field is exact
    np.testing.assert_allclose(out[3:9, got[1]], truth[3:9, 1], atol=1e-10)
    np.testing.assert_allclose(out[10:, got[3]], truth[10:, 3], atol=1e-10)
    np.testing.assert_allclose(out[6, got[2]], 0.5 * (truth[5, 2] + truth[7, 2]))
    assert np.abs(out[6, got[2]] - truth[6, 2]).max() > 1e-4  # (in time, which is not exact here)
    seen = ~np.isnan(m[:, keep]).any(axis=2)
    np.testing.assert_array_equal(out[seen], m[:, keep][seen])  # seen samples untouched
    assert SHORT_GAP >= 1


def test_markers_in_one_plane_fall_back_to_time_interpolation():
    t, rest, truth = _affine_tracks()
    rest[:, 2] = 0.0  # every marker on one plane: the spline's affine part is not determined
    truth = rest[None] + (truth - truth[:1]) * np.array([1.0, 1.0, 0.0])
    m = truth.copy()
    m[:4, 0] = np.nan
    out, _ = fill_marker_gaps(t, m, rest)
    np.testing.assert_array_equal(out[:4, 0], np.repeat(truth[4:5, 0], 4, axis=0))


def test_the_initial_trajectory_follows_markers_seen_late(tmp_path):
    """Half the markers unseen in the first half of a release: the constrained trajectory puts
    their vertices near where the truth has them then, not where they are first seen."""
    sc = load_scene(small_bar_case(tmp_path))
    rec = sc.recordings_with_role("train")[0]
    m = rec.markers.copy()
    T, K = m.shape[:2]
    late = np.arange(0, K, 2)
    m[: T // 2, late] = np.nan
    masked = Recording(rec.times, rec.marker_rest, m, at_rest_initially=rec.at_rest_initially)
    _, X_full, idx = initial_trajectory(sc, sc.model(), rec)
    _, X, idx_m = initial_trajectory(sc, sc.model(), masked)
    np.testing.assert_array_equal(idx, idx_m)
    motion = np.abs(X_full[: len(X_full) // 2] - X_full[len(X_full) // 2]).max()
    err = np.abs(X[: len(X) // 2] - X_full[: len(X_full) // 2]).max()
    # from the 6 markers left in those frames: 0.20x the motion; held where first seen, 1.0x
    assert motion > 1e-3 and err < 0.3 * motion, (err, motion)
