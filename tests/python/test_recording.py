"""Recording .npz format (docs/formats.md): roundtrip, exact keys, validation, point-cloud folders."""
import numpy as np
import pytest

from matlearn.recording import Recording, load_cloud_folder, load_recording, save_recording


def _rec(T=4, K=3, **kw):
    rng = np.random.default_rng(0)
    times = np.cumsum(rng.uniform(0.001, 0.01, T))  # non-uniform, not multiples of a step
    rest = rng.normal(size=(K, 3))
    markers = rest[None] + 0.01 * rng.normal(size=(T, K, 3))
    markers[1, 0] = np.nan
    markers[2, :] = np.nan
    return Recording(times, rest, markers, **kw)


def test_roundtrip_keeps_everything(tmp_path):
    rng = np.random.default_rng(1)
    rec = _rec()
    T = rec.num_frames
    counts = [2, 0, 3, 1]
    rec = Recording(rec.times, rec.marker_rest, rec.markers,
                    cloud_points=rng.normal(size=(sum(counts), 3)),
                    cloud_offsets=np.concatenate([[0], np.cumsum(counts)]), cloud_sigma=0.002,
                    at_rest_initially=True, drive_rest=np.zeros((2, 3)),
                    drive=rng.normal(size=(T, 2, 3)))
    path = save_recording(rec, tmp_path / "r.npz")
    back = load_recording(path)
    for key in ("times", "marker_rest", "markers", "cloud_points", "cloud_offsets", "drive_rest", "drive"):
        np.testing.assert_array_equal(getattr(back, key), getattr(rec, key), err_msg=key)
    assert back.cloud_sigma == 0.002 and back.at_rest_initially is True
    assert back.cloud_offsets.dtype == np.int64
    np.testing.assert_array_equal(back.cloud(2), rec.cloud_points[2:5])
    np.testing.assert_array_equal(back.seen[1], [False, True, True])
    assert not back.seen[2].any()


def test_exact_format_keys_and_dtypes(tmp_path):
    save_recording(_rec(), tmp_path / "r.npz")
    with np.load(tmp_path / "r.npz") as z:
        assert set(z.files) == {"times", "marker_rest", "markers", "at_rest_initially"}
        assert z["times"].dtype == np.float64 and z["markers"].shape == (4, 3, 3)


def test_reads_file_written_by_a_foreign_tool(tmp_path):
    times = np.array([0.0, 0.0013, 0.0041])
    rest = np.eye(3)
    np.savez(tmp_path / "ext.npz", times=times, marker_rest=rest, markers=np.stack([rest] * 3))
    rec = load_recording(tmp_path / "ext.npz")
    assert rec.at_rest_initially is False and rec.cloud_points is None and not rec.has_drive
    np.testing.assert_array_equal(rec.times, times)


def test_cloud_only_recording():
    rec = Recording([0.0, 0.1], cloud_points=np.zeros((5, 3)), cloud_offsets=[0, 2, 5])
    assert rec.num_markers == 0 and rec.markers.shape == (2, 0, 3) and len(rec.cloud(1)) == 3


T3 = np.array([0.0, 0.1, 0.2])
R2 = np.zeros((2, 3))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(times=[0.0, 0.1, 0.1], marker_rest=R2, markers=np.zeros((3, 2, 3))), "strictly increasing"),
        (dict(times=[0.0, 0.2, 0.1], marker_rest=R2, markers=np.zeros((3, 2, 3))), "strictly increasing"),
        (dict(times=[[0.0, 0.1]], marker_rest=R2, markers=np.zeros((1, 2, 3))), "times"),
        (dict(times=T3, marker_rest=R2, markers=np.zeros((2, 2, 3))), r"markers: expected shape \(T, K, 3\) = \(3, 2, 3\)"),
        (dict(times=T3, marker_rest=np.zeros((2, 2)), markers=np.zeros((3, 2, 3))), "marker_rest"),
        (dict(times=T3, marker_rest=R2, markers=np.full((3, 2, 3), np.nan)), "every marker is NaN"),
        (dict(times=T3, marker_rest=R2, markers=np.where(np.arange(3) == 0, np.nan, np.zeros((3, 2, 3)))), "partly NaN"),
        (dict(times=T3, marker_rest=R2, markers=np.full((3, 2, 3), np.inf)), "Inf"),
        (dict(times=T3), "markers, point clouds, or both"),
        (dict(times=T3, cloud_points=np.zeros((4, 3)), cloud_offsets=[0, 1, 4]), r"cloud_offsets: expected shape \(T\+1,\)"),
        (dict(times=T3, cloud_points=np.zeros((4, 3)), cloud_offsets=[0, 1, 2, 3]), "end at len"),
        (dict(times=T3, cloud_points=np.zeros((4, 3)), cloud_offsets=[0, 3, 1, 4]), "non-decreasing"),
        (dict(times=T3, cloud_points=np.zeros((4, 3)), cloud_offsets=[0, 1, 2, 4], cloud_sigma=-1.0), "cloud_sigma"),
        (dict(times=T3, marker_rest=R2, markers=np.zeros((3, 2, 3)), cloud_sigma=0.0), "cloud_sigma: must be > 0"),
        (dict(times=T3, marker_rest=R2, markers=np.zeros((3, 2, 3)), drive_rest=np.zeros((1, 3)),
              drive=np.zeros((2, 1, 3))), "drive: expected shape"),
        (dict(times=T3, marker_rest=R2, markers=np.zeros((3, 2, 3)), drive_rest=np.zeros((1, 3))), "together"),
    ],
)
def test_validation_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Recording(**kwargs)


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        load_recording(tmp_path / "nope.npz")
    np.savez(tmp_path / "bad.npz", marker_rest=R2)
    with pytest.raises(ValueError, match="missing required key 'times'"):
        load_recording(tmp_path / "bad.npz")
    np.savez(tmp_path / "bad2.npz", times=[0.0, 0.1], marker_rest=R2, markers=np.zeros((3, 2, 3)))
    with pytest.raises(ValueError, match="bad2.npz: markers"):
        load_recording(tmp_path / "bad2.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(ValueError, match="junk.npz: not a NumPy .npz archive"):
        load_recording(tmp_path / "junk.npz")
    np.save(tmp_path / "plain.npy", np.zeros(3))  # a single .npy, not an archive
    with pytest.raises(ValueError, match="not a NumPy .npz archive"):
        load_recording(tmp_path / "plain.npy")


@pytest.mark.parametrize("flag", ["False", "no", np.array([True, False]), 2, 0.5])
def test_at_rest_initially_must_be_a_boolean(tmp_path, flag):
    """The string "False" was read as True (bool("False")): the recording replayed from rest."""
    with pytest.raises(ValueError, match="at_rest_initially: expected a boolean"):
        _rec(at_rest_initially=flag)
    rec = _rec()
    np.savez(tmp_path / "r.npz", times=rec.times, marker_rest=rec.marker_rest, markers=rec.markers,
             at_rest_initially=np.asarray(flag))
    with pytest.raises(ValueError, match="r.npz: at_rest_initially"):
        load_recording(tmp_path / "r.npz")


@pytest.mark.parametrize("flag", [True, False, np.True_, np.array(False), 1, 0])
def test_at_rest_initially_accepts_booleans_and_0_1(tmp_path, flag):
    assert _rec(at_rest_initially=flag).at_rest_initially is bool(flag)
    with pytest.raises(ValueError, match="at_rest_initially"):
        _rec(at_rest_initially=None)


def test_cloud_folder_ply_and_pcd(tmp_path):
    import trimesh

    rng = np.random.default_rng(2)
    a, b, c = rng.normal(size=(4, 3)), rng.normal(size=(6, 3)), rng.normal(size=(3, 3))
    trimesh.PointCloud(a).export(tmp_path / "f0.ply")
    header = "VERSION .7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
    rows = "\n".join(" ".join(f"{v:.9g}" for v in (*p, 1.0)) for p in b)
    (tmp_path / "f1.pcd").write_text(f"# .PCD\n{header}WIDTH 6\nHEIGHT 1\nPOINTS 6\nDATA ascii\n{rows}\n")
    binary = np.concatenate([c, np.ones((3, 1))], axis=1).astype("<f4").tobytes()
    (tmp_path / "f2.pcd").write_bytes(
        f"{header}WIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA binary\n".encode() + binary
    )
    (tmp_path / "times.txt").write_text("0.0\n0.033\n0.071\n")
    rec = load_cloud_folder(tmp_path, cloud_sigma=0.001)
    np.testing.assert_array_equal(rec.cloud_offsets, [0, 4, 10, 13])
    np.testing.assert_allclose(rec.cloud(0), a, atol=1e-6)
    np.testing.assert_allclose(rec.cloud(1), b, atol=1e-6)
    np.testing.assert_allclose(rec.cloud(2), c, atol=1e-6)
    np.testing.assert_allclose(rec.times, [0.0, 0.033, 0.071])
    (tmp_path / "times.txt").write_text("0.0\n0.033\n")
    with pytest.raises(ValueError, match="3 .ply/.pcd files but 2 times"):
        load_cloud_folder(tmp_path)
    with pytest.raises(FileNotFoundError):
        load_cloud_folder(tmp_path / "missing")


def test_a_cloud_folder_is_a_recording_and_its_frames_sort_by_number(tmp_path):
    """formats.md: a folder of per-frame clouds + times.txt is the equivalent cloud-only
    recording, so a scene may name it (load_recording); unpadded frame numbers keep their order."""
    import trimesh

    rng = np.random.default_rng(3)
    clouds = [rng.normal(size=(3 + i, 3)) for i in range(12)]
    folder = tmp_path / "scans"
    folder.mkdir()
    for i, c in enumerate(clouds):  # frame_2 must come before frame_10
        trimesh.PointCloud(c).export(folder / f"frame_{i}.ply")
    (folder / "times.txt").write_text("\n".join(f"{0.01 * i:.2f}" for i in range(12)))
    rec = load_recording(folder)
    assert rec.num_markers == 0 and rec.num_frames == 12
    for i, c in enumerate(clouds):
        np.testing.assert_allclose(rec.cloud(i), c, atol=1e-6)
