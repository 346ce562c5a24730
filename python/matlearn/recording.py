"""Recordings of a moving object: tracked markers and/or raw point clouds over time.

The on-disk format is the `.npz` archive of docs/formats.md, read and written exactly:
`times`, `marker_rest`, `markers` (NaN = unseen), optional `cloud_points`, `cloud_offsets`,
`cloud_sigma` and `at_rest_initially`.

matlearn extension (optional keys, ignored by tools that do not know them):

* `drive_rest` (D, 3): rest-space positions of *driven* points, i.e. points whose motion is
  prescribed by the experiment rather than observed (a keyframed cap pushed by a robot, a moving
  clamp). `drive` (T, D, 3): their positions at `times`. Replay prescribes the model vertices at
  (or nearest to) these points to follow them, interpolated linearly in time between samples.

A folder of per-frame `.ply`/`.pcd` clouds plus `times.txt` is read by :func:`load_cloud_folder`,
and by :func:`load_recording` wherever a recording is named (formats.md: the cloud-only equivalent).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMAT_KEYS = (
    "times",
    "marker_rest",
    "markers",
    "cloud_points",
    "cloud_offsets",
    "cloud_sigma",
    "at_rest_initially",
)
EXTENSION_KEYS = ("drive_rest", "drive")


@dataclass
class Recording:
    """One recording. Shapes: times (T,), marker_rest (K, 3), markers (T, K, 3) with NaN where a
    marker is unseen; clouds as concatenated points (N, 3) with offsets (T+1,); drive points
    (D, 3) rest and (T, D, 3) trajectories. Arrays are converted and validated on construction
    (ValueError with the offending key and shape)."""

    times: np.ndarray
    marker_rest: np.ndarray | None = None
    markers: np.ndarray | None = None
    cloud_points: np.ndarray | None = None
    cloud_offsets: np.ndarray | None = None
    cloud_sigma: float | None = None
    at_rest_initially: bool = False
    drive_rest: np.ndarray | None = None
    drive: np.ndarray | None = None

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64)
        if self.times.ndim != 1 or len(self.times) < 1:
            raise ValueError(f"times: expected shape (T,) with T >= 1, got {self.times.shape}")
        if not np.all(np.isfinite(self.times)):
            raise ValueError("times: contains NaN or Inf")
        if np.any(np.diff(self.times) <= 0):
            i = int(np.argmax(np.diff(self.times) <= 0))
            raise ValueError(
                f"times: must be strictly increasing (times[{i}] = {self.times[i]} >= "
                f"times[{i + 1}] = {self.times[i + 1]})"
            )
        T = len(self.times)
        if self.marker_rest is None and self.markers is None:
            self.marker_rest = np.zeros((0, 3))
            self.markers = np.zeros((T, 0, 3))
        elif self.marker_rest is None or self.markers is None:
            raise ValueError("marker_rest and markers must be given together")
        self.marker_rest = np.asarray(self.marker_rest, dtype=np.float64)
        self.markers = np.asarray(self.markers, dtype=np.float64)
        if self.marker_rest.ndim != 2 or self.marker_rest.shape[1] != 3:
            raise ValueError(f"marker_rest: expected shape (K, 3), got {self.marker_rest.shape}")
        K = len(self.marker_rest)
        if not np.all(np.isfinite(self.marker_rest)):
            raise ValueError("marker_rest: contains NaN or Inf")
        if self.markers.shape != (T, K, 3):
            raise ValueError(
                f"markers: expected shape (T, K, 3) = ({T}, {K}, 3) from times and marker_rest, "
                f"got {self.markers.shape}"
            )
        if np.any(np.isinf(self.markers)):
            raise ValueError("markers: contains Inf (use NaN for unseen markers)")
        if K > 0:
            seen = self.seen
            # A marker is seen or not as a whole: a partly NaN xyz is malformed.
            partial = np.isnan(self.markers).any(axis=2) & ~np.isnan(self.markers).all(axis=2)
            if np.any(partial):
                t, k = np.argwhere(partial)[0]
                raise ValueError(f"markers: frame {t}, marker {k} is only partly NaN {self.markers[t, k]}")
            if not np.any(seen):
                raise ValueError("markers: every marker is NaN in every frame (nothing observed)")
        self._validate_clouds(T)
        if K == 0 and self.cloud_points is None:
            raise ValueError("a recording needs markers, point clouds, or both")
        self._validate_drive(T)
        self.at_rest_initially = _flag(self.at_rest_initially, "at_rest_initially")

    def _validate_clouds(self, T: int) -> None:
        given = [k for k in ("cloud_points", "cloud_offsets") if getattr(self, k) is not None]
        if len(given) == 1:
            raise ValueError("cloud_points and cloud_offsets must be given together")
        if self.cloud_sigma is not None:  # checked with or without clouds (a tracked recording keeps it)
            self.cloud_sigma = float(self.cloud_sigma)
            if not self.cloud_sigma > 0:
                raise ValueError(f"cloud_sigma: must be > 0 (m), got {self.cloud_sigma}")
        if not given:
            return
        self.cloud_points = np.asarray(self.cloud_points, dtype=np.float64)
        if self.cloud_points.ndim != 2 or self.cloud_points.shape[1] != 3:
            raise ValueError(f"cloud_points: expected shape (N, 3), got {self.cloud_points.shape}")
        if not np.all(np.isfinite(self.cloud_points)):
            raise ValueError("cloud_points: contains NaN or Inf")
        off = np.asarray(self.cloud_offsets)
        if off.ndim != 1 or len(off) != T + 1:
            raise ValueError(f"cloud_offsets: expected shape (T+1,) = ({T + 1},), got {off.shape}")
        if not np.issubdtype(off.dtype, np.integer):
            if np.any(off != np.round(off)):
                raise ValueError("cloud_offsets: must be integers")
        off = off.astype(np.int64)
        if off[0] != 0 or off[-1] != len(self.cloud_points) or np.any(np.diff(off) < 0):
            raise ValueError(
                f"cloud_offsets: must start at 0, be non-decreasing and end at len(cloud_points) = "
                f"{len(self.cloud_points)}; got first {off[0]}, last {off[-1]}"
            )
        self.cloud_offsets = off

    def _validate_drive(self, T: int) -> None:
        if (self.drive_rest is None) != (self.drive is None):
            raise ValueError("drive_rest and drive must be given together")
        if self.drive_rest is None:
            return
        self.drive_rest = np.asarray(self.drive_rest, dtype=np.float64)
        self.drive = np.asarray(self.drive, dtype=np.float64)
        if self.drive_rest.ndim != 2 or self.drive_rest.shape[1] != 3 or len(self.drive_rest) == 0:
            raise ValueError(f"drive_rest: expected shape (D, 3) with D >= 1, got {self.drive_rest.shape}")
        D = len(self.drive_rest)
        if self.drive.shape != (T, D, 3):
            raise ValueError(f"drive: expected shape (T, D, 3) = ({T}, {D}, 3), got {self.drive.shape}")
        if not (np.all(np.isfinite(self.drive)) and np.all(np.isfinite(self.drive_rest))):
            raise ValueError("drive/drive_rest: driven points must be finite in every frame")

    # ------------------------------------------------------------------ views
    @property
    def num_frames(self) -> int:
        return len(self.times)

    @property
    def num_markers(self) -> int:
        return len(self.marker_rest)

    @property
    def seen(self) -> np.ndarray:
        """(T, K) bool: marker k is seen in frame t."""
        return ~np.isnan(self.markers).any(axis=2)

    @property
    def has_clouds(self) -> bool:
        return self.cloud_points is not None

    @property
    def has_drive(self) -> bool:
        return self.drive_rest is not None

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def cloud(self, t: int) -> np.ndarray:
        """Frame t's point cloud (N_t, 3)."""
        if not self.has_clouds:
            raise ValueError("this recording has no point clouds")
        return self.cloud_points[self.cloud_offsets[t] : self.cloud_offsets[t + 1]]


def save_recording(rec: Recording, path) -> Path:
    """Write `rec` as an uncompressed `.npz` with exactly the formats.md keys (plus the drive
    extension keys when present)."""
    path = Path(path)
    data = {
        "times": rec.times,
        "marker_rest": rec.marker_rest,
        "markers": rec.markers,
        "at_rest_initially": np.array(bool(rec.at_rest_initially)),
    }
    if rec.has_clouds:
        data["cloud_points"] = rec.cloud_points
        data["cloud_offsets"] = rec.cloud_offsets.astype(np.int64)
    if rec.cloud_sigma is not None:
        data["cloud_sigma"] = np.array(float(rec.cloud_sigma))
    if rec.has_drive:
        data["drive_rest"] = rec.drive_rest
        data["drive"] = rec.drive
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:  # a file object keeps numpy from appending ".npz"
        np.savez(f, **data)
    return path


def _flag(value, key: str) -> bool:
    """A boolean scalar (True/False, numpy bool, or the integers 0/1); anything else, e.g. the
    string "False", which Python would read as True, raises a ValueError naming `key`."""
    v = np.asarray(value)
    if v.shape == () and (v.dtype.kind == "b" or (v.dtype.kind in "iu" and v.item() in (0, 1))):
        return bool(v.item())
    raise ValueError(f"{key}: expected a boolean scalar (True or False), got {value!r}")


def load_recording(path) -> Recording:
    """Read a recording: a `.npz` archive (formats.md), or a folder of per-frame `.ply`/`.pcd`
    point clouds with a `times.txt` (`load_cloud_folder`, the cloud-only equivalent); raises
    FileNotFoundError / ValueError naming the file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"recording not found: {path}")
    if path.is_dir():
        return load_cloud_folder(path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":  # an .npz is a zip archive of .npy arrays
        raise ValueError(f"{path}: not a NumPy .npz archive (write it with numpy.savez or "
                         "matlearn.recording.save_recording)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as err:  # zipfile/format errors are not informative on their own
        raise ValueError(f"{path}: not a readable .npz archive ({err})") from err
    if "times" not in data:
        raise ValueError(f"{path}: missing required key 'times' (keys: {sorted(data)})")
    kwargs = {k: data[k] for k in FORMAT_KEYS + EXTENSION_KEYS if k in data}
    if "cloud_sigma" in kwargs:
        kwargs["cloud_sigma"] = float(kwargs["cloud_sigma"])
    try:
        return Recording(**kwargs)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from err


# ---------------------------------------------------------------------------- point clouds
def _read_pcd(path: Path) -> np.ndarray:
    """x, y, z of a PCD file (ASCII or binary, uncompressed)."""
    raw = path.read_bytes()
    header, pos = {}, 0
    while True:
        end = raw.index(b"\n", pos)
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
    fields = header.get("FIELDS", [])
    if not all(c in fields for c in "xyz"):
        raise ValueError(f"{path}: PCD without x, y, z fields (FIELDS {fields})")
    sizes = [int(s) for s in header.get("SIZE", ["4"] * len(fields))]
    types = header.get("TYPE", ["F"] * len(fields))
    counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
    n = int(header.get("POINTS", header.get("WIDTH", ["0"]))[0])
    mode = header["DATA"][0].lower()
    cols = []
    for name, cnt in zip(fields, counts):
        cols += [name] if cnt == 1 else [f"{name}_{i}" for i in range(cnt)]
    if mode == "ascii":
        rows = [ln.split() for ln in raw[pos:].decode("ascii", "replace").splitlines() if ln.strip()]
        arr = np.array(rows[:n], dtype=np.float64).reshape(-1, len(cols))
        return arr[:, [cols.index(c) for c in "xyz"]]
    if mode == "binary":
        kind = {"F": "f", "I": "i", "U": "u"}
        dt = np.dtype(
            [(name, f"<{kind[t]}{s}", (c,) if c > 1 else ()) for name, s, t, c in zip(fields, sizes, types, counts)]
        )
        arr = np.frombuffer(raw, dtype=dt, count=n, offset=pos)
        return np.stack([arr[c].astype(np.float64) for c in "xyz"], axis=1)
    raise ValueError(f"{path}: PCD DATA mode {mode!r} not supported (ascii or binary only)")


def _read_cloud(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".pcd":
        pts = _read_pcd(path)
    else:
        import trimesh

        geom = trimesh.load(path, process=False)
        pts = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)]  # scanners write NaN for missing returns
    return pts.reshape(-1, 3)


def _frame_order(path: Path):
    """Sort key of a per-frame file: its name with every run of digits compared as a number, so
    frame_2 comes before frame_10 (scanners seldom zero-pad)."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", path.name)]


def load_cloud_folder(folder, cloud_sigma: float | None = None) -> Recording:
    """A cloud-only recording from a folder of per-frame `.ply`/`.pcd` files (in name order, runs
    of digits compared as numbers: `_frame_order`) and `times.txt` (one time in s per line, one
    line per file)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"point-cloud folder not found: {folder}")
    tfile = folder / "times.txt"
    if not tfile.exists():
        raise FileNotFoundError(f"{folder}: missing times.txt (one time per frame, in s)")
    times = np.array([float(x) for x in tfile.read_text().split()])
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in (".ply", ".pcd")), key=_frame_order)
    if len(files) != len(times):
        raise ValueError(f"{folder}: {len(files)} .ply/.pcd files but {len(times)} times in times.txt")
    clouds = [_read_cloud(p) for p in files]
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)
    pts = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    return Recording(times, cloud_points=pts, cloud_offsets=offsets, cloud_sigma=cloud_sigma)
