"""Scenes: a mesh, the nominal material and damping, the clamp, the time step and the recordings.

`scene.toml` is read and written exactly in the layout of docs/formats.md. Relative paths are
relative to the scene file. Optional keys that matlearn adds (documented, ignored elsewhere):
`[material] edits` (designed material bumps), `[damping] mass_poly` / `stiffness_poly`
(strain-dependent Rayleigh coefficients). Defaults for optional sections: no `[damping]` means no
damping, no `[boundary]` means no clamped vertex, no `gravity` means [0, -9.81, 0].
"""
from __future__ import annotations

try:
    import tomllib
except ImportError:  # Python < 3.11
    import tomli as tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import meshes
from .materials import Damping, Material, make_model
from .recording import Recording, load_recording

ROLES = ("train", "test")
DEFAULT_GRAVITY = (0.0, -9.81, 0.0)


def vertices_in_box(vertices: np.ndarray, box) -> np.ndarray:
    """Indices of the rest vertices inside the closed box [[x0, y0, z0], [x1, y1, z1]]."""
    b = np.asarray(box, dtype=np.float64)
    if b.shape != (2, 3):
        raise ValueError(f"box: expected [[x0, y0, z0], [x1, y1, z1]], got shape {b.shape}")
    lo, hi = np.minimum(b[0], b[1]), np.maximum(b[0], b[1])
    V = np.asarray(vertices)
    return np.flatnonzero(np.all((V >= lo) & (V <= hi), axis=1))


@dataclass
class Scene:
    """A loaded scene. `recordings` holds (absolute path, role) pairs; `fixed` the clamped vertex
    indices; `fixed_box` the box they came from (None when read from a fixed_vertices file)."""

    mesh: object
    material: Material
    damping: Damping = field(default_factory=Damping)
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    time_step: float = 1e-3
    gravity: tuple = DEFAULT_GRAVITY
    recordings: list = field(default_factory=list)
    path: Path | None = None
    fixed_box: list | None = None
    mesh_file: Path | None = None
    mesh_options: dict = field(default_factory=dict)

    def __post_init__(self):
        self.fixed = np.asarray(self.fixed, dtype=np.int64).ravel()
        if len(self.fixed) and (self.fixed.min() < 0 or self.fixed.max() >= self.mesh.num_vertices):
            raise ValueError(f"fixed vertices out of range [0, {self.mesh.num_vertices})")
        if not self.time_step > 0:
            raise ValueError(f"time_step must be > 0 (s), got {self.time_step}")
        g = np.asarray(self.gravity, dtype=np.float64)
        if g.shape != (3,):
            raise ValueError(f"gravity: expected 3 components, got {self.gravity}")
        self.gravity = tuple(float(x) for x in g)
        for _, role in self.recordings:
            if role not in ROLES:
                raise ValueError(f"recording role must be one of {ROLES}, got {role!r}")

    @property
    def object_size(self) -> float:
        """Rest bounding-box diagonal (m)."""
        return meshes.object_size(self.mesh)

    @property
    def directory(self) -> Path:
        return self.path.parent if self.path is not None else Path.cwd()

    def model(self, correction=None, material: Material | None = None, damping: Damping | None = None):
        """The C++ model of this scene's nominal material (or the given one) plus a correction."""
        return make_model(self.mesh, material or self.material, damping or self.damping, correction)

    def integrator(self, model=None, max_newton: int = 8, tolerance: float = 1e-7):
        """A backward-Euler integrator with this scene's clamp, time step and gravity."""
        from . import _core

        model = model if model is not None else self.model()
        return _core.time.Integrator(
            model, self.fixed, self.time_step, np.array(self.gravity), max_newton, tolerance
        )

    def recording_paths(self, role: str | None = None) -> list[Path]:
        return [p for p, r in self.recordings if role is None or r == role]

    def recordings_with_role(self, role: str) -> list[Recording]:
        """Load the recordings of a role ("train" or "test"), in scene order."""
        if role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {role!r}")
        out = []
        for p in self.recording_paths(role):
            rec = load_recording(p)
            self.check_recording(rec, f"{role} recording {Path(p).name}")
            out.append(rec)
        return out

    def check_points(self, points, what: str) -> None:
        """Raise a ValueError when a rest-space point lies farther than MARKER_DISTANCE_MAX x the
        object size from the mesh (points in other units than the scene's, or of another body);
        `what` names the points ("<recording>: marker")."""
        from .embedding import embed_points

        size = self.object_size
        far = np.asarray(embed_points(self.mesh, points).distance, float)
        if far.size and far.max() > MARKER_DISTANCE_MAX * size:
            k = int(np.argmax(far))
            raise ValueError(
                f"{what} {k}'s rest position {np.round(np.asarray(points)[k], 6).tolist()} lies {far[k]:.4g} m "
                f"from the model's mesh (object size {size:.4g} m); rest positions must be on or near the "
                f"body, in the scene's units (m)")

    def check_recording(self, rec: Recording, label: str) -> None:
        """Raise a ValueError naming `label` when `rec`'s markers cannot be in this scene's units
        (m): a marker's (or drive point's) rest position farther than MARKER_DISTANCE_MAX x the
        object size from the mesh, or, on a clamped body, a marker seen farther than
        MARKER_TRAVEL_MAX x the object size from its rest position (e.g. markers in mm on a model
        in m). Warns when 4+ markers span less than MARKER_SPREAD_MIN x the object (a mesh in mm,
        markers in m) or frames lie FRAME_INTERVAL_WARN apart (times in ms). Point clouds are not
        checked."""
        dt = float(np.median(np.diff(rec.times))) if len(rec.times) > 1 else 0.0
        if dt >= FRAME_INTERVAL_WARN:
            steps = rec.duration / self.time_step
            warnings.warn(f"{label}: its frames are {dt:.4g} s apart (median): are its times in seconds? "
                          f"(its {rec.duration:.4g} s take {steps:,.0f} time steps of {self.time_step:g} s "
                          "to simulate)", stacklevel=2)
        size = self.object_size
        if rec.has_drive:
            self.check_points(rec.drive_rest, f"{label}: drive point")
        if rec.num_markers == 0:
            return
        self.check_points(rec.marker_rest, f"{label}: marker")
        if rec.markers is not None:
            never = np.flatnonzero(~rec.seen.any(axis=0))
            if len(never):
                warnings.warn(f"{label}: marker(s) {never[:10].tolist()}{' ...' if len(never) > 10 else ''} "
                              f"({len(never)} of {rec.num_markers}) never seen (NaN in every frame): they "
                              "carry no information", stacklevel=2)
        rest = np.asarray(rec.marker_rest, float)
        spread = float(np.linalg.norm(np.ptp(rest, axis=0))) if len(rest) >= 4 else None
        if spread is not None and spread < MARKER_SPREAD_MIN * size:
            warnings.warn(f"{label}: its {len(rest)} markers span {spread:.4g} m, {size / max(spread, 1e-300):.3g}x "
                          f"less than the object ({size:.4g} m): are the mesh and the recording in the same "
                          "units (m)?", stacklevel=2)
        if len(self.fixed) and rec.markers is not None:
            travel = np.linalg.norm(np.asarray(rec.markers, float) - np.asarray(rec.marker_rest, float)[None],
                                    axis=2)
            travel = np.where(np.isfinite(travel), travel, 0.0)
            if travel.max(initial=0.0) > MARKER_TRAVEL_MAX * size:
                t, k = np.unravel_index(int(np.argmax(travel)), travel.shape)
                raise ValueError(
                    f"{label}: marker {k} is seen {travel[t, k]:.4g} m from its rest position at "
                    f"t = {rec.times[t]:.4g} s, {travel[t, k] / size:.3g}x the clamped object's size "
                    f"({size:.4g} m): are markers and marker_rest in the same units (m)?")


# the keys scene.toml may hold (formats.md, and matlearn's extensions in data.md); anything else
# is reported (a misspelt optional key would otherwise silently fall back to its default)
SCHEMA = {
    "mesh": ("file", "max_volume", "min_ratio"),
    "material": ("model", "youngs_modulus", "poisson_ratio", "density", "edits"),
    "damping": ("alpha_mass", "alpha_stiffness", "mass_poly", "stiffness_poly"),
    "boundary": ("fixed_box", "fixed_vertices"),
    "simulation": ("time_step", "gravity"),
    "recording": ("file", "role"),
}
# a marker's rest position farther than this x the object size from the mesh: other units
MARKER_DISTANCE_MAX = 0.1
# a clamped body's marker farther than this x the object size from its rest position: other units
MARKER_TRAVEL_MAX = 5.0
# 4 or more markers spanning less than this x the object size: warned (a mesh in mm, markers in m)
MARKER_SPREAD_MIN = 0.01
# frames further apart than this (s, median): warned (times in ms read as s)
FRAME_INTERVAL_WARN = 0.5


def _did_you_mean(name: str, options) -> str:
    import difflib

    close = difflib.get_close_matches(name, list(options), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _check_keys(doc: dict, path: Path) -> None:
    """Warn about every section and key scene.toml does not define (a typo such as
    `alpha_stifness` or `[dampng]` would otherwise silently leave the default in place)."""
    for name, value in doc.items():
        if name not in SCHEMA:
            warnings.warn(f"{path}: unknown {'section' if isinstance(value, (dict, list)) else 'key'} "
                          f"'{name}' ignored{_did_you_mean(name, SCHEMA)}", stacklevel=3)
            continue
        tables = value if isinstance(value, list) else [value]
        for table in tables:
            if not isinstance(table, dict):
                raise ValueError(f"{path}: '{name}' must be a table ([{name}])")
            for key in table:
                if key not in SCHEMA[name]:
                    warnings.warn(f"{path}: unknown key '{key}' in [{name}] ignored"
                                  f"{_did_you_mean(key, SCHEMA[name])}", stacklevel=3)


def _require(table: dict, key: str, where: str, path: Path):
    if key not in table:
        raise ValueError(f"{path}: missing key '{key}' in [{where}]"
                         f"{_did_you_mean(key, [k for k in table if k not in SCHEMA[where]])}")
    return table[key]


def _number(value, key: str, where: str, path: Path) -> float:
    """float(value), or a ValueError naming the key and the value."""
    if isinstance(value, bool):
        raise ValueError(f"{path}: [{where}] {key} must be a number, got {value!r}")
    if isinstance(value, str):
        raise ValueError(f"{path}: [{where}] {key} must be a number, got the string {value!r} (write it without quotes)")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: [{where}] {key} must be a number, got {value!r}") from None
    if not np.isfinite(x):
        raise ValueError(f"{path}: [{where}] {key} must be a finite number, got {value!r}")
    return x


def _text(value, key: str, where: str, path: Path) -> str:
    """A file name given as a TOML string, or a ValueError naming the key."""
    if not isinstance(value, str):
        raise ValueError(f"{path}: [{where}] {key} must be a file name in quotes, got {value!r}")
    return value


def _numbers(value, key: str, where: str, path: Path, length: int | None = None) -> list:
    """[float, ...] from a TOML array, or a ValueError naming the key."""
    if not isinstance(value, (list, tuple)) or (length is not None and len(value) != length):
        want = f"an array of {length} numbers" if length else "an array of numbers"
        raise ValueError(f"{path}: [{where}] {key} must be {want}, got {value!r}")
    return [_number(v, key, where, path) for v in value]


def clamp_weakness(vertices, fixed) -> str | None:
    """Why the clamped vertices `fixed` cannot hold a body by themselves (None when they can, or
    when nothing is clamped: a free or drive-held body): fewer than 3 of them, or all on one line,
    leave a rigid rotation free, so a static solve (held poses, `--release`) has no unique
    equilibrium. Dynamic steps still run (the mass term holds them); drive points may hold it."""
    fixed = np.unique(np.asarray(fixed, np.int64))
    if len(fixed) == 0:
        return None
    P = np.asarray(vertices, float)[fixed]
    if len(fixed) < 3:
        return (f"clamps only {len(fixed)} vertex(es): the body can rotate about them, and static "
                "solves (held poses, releases) will fail; widen the clamp")
    sv = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300):
        return (f"clamps {len(fixed)} vertices that all lie on one line: the body can rotate about "
                "it, and static solves (held poses, releases) will fail; widen the clamp")
    return None


def load_scene(path) -> Scene:
    """Read a `scene.toml` (formats.md). Raises FileNotFoundError for missing files and
    ValueError naming the section and key for malformed content."""
    path = Path(path).resolve()
    if not path.exists():
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path}: invalid TOML ({err})") from err
    base = path.parent
    _check_keys(doc, path)
    for section in ("mesh", "material", "simulation"):
        if section not in doc:
            raise ValueError(f"{path}: missing section [{section}]"
                             f"{_did_you_mean(section, [k for k in doc if k not in SCHEMA])}")

    m = doc["mesh"]
    mesh_file = base / _text(_require(m, "file", "mesh", path), "file", "mesh", path)
    opts = {k: _number(m[k], k, "mesh", path) for k in ("max_volume", "min_ratio") if k in m}
    mesh = meshes.load_mesh(mesh_file, **opts)

    mat = doc["material"]
    try:
        material = Material(
            model=_require(mat, "model", "material", path),
            youngs_modulus=_number(_require(mat, "youngs_modulus", "material", path), "youngs_modulus",
                                   "material", path),
            poisson_ratio=_number(_require(mat, "poisson_ratio", "material", path), "poisson_ratio",
                                  "material", path),
            density=_number(_require(mat, "density", "material", path), "density", "material", path),
            edits=[tuple(_numbers(e, "edits", "material", path, 3)) for e in mat.get("edits", [])],
        )
        d = doc.get("damping", {})
        damping = Damping(
            alpha_mass=_number(d.get("alpha_mass", 0.0), "alpha_mass", "damping", path),
            alpha_stiffness=_number(d.get("alpha_stiffness", 0.0), "alpha_stiffness", "damping", path),
            mass_poly=_numbers(d.get("mass_poly", []), "mass_poly", "damping", path),
            stiffness_poly=_numbers(d.get("stiffness_poly", []), "stiffness_poly", "damping", path),
        )
    except ValueError as err:
        msg = str(err)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None

    b = doc.get("boundary", {})
    fixed_box = None
    if "fixed_box" in b and "fixed_vertices" in b:
        raise ValueError(f"{path}: [boundary] has both fixed_box and fixed_vertices; give one")
    if "fixed_box" in b:
        rows = b["fixed_box"]
        if not isinstance(rows, list) or len(rows) != 2:
            raise ValueError(f"{path}: [boundary] fixed_box must be [[x0, y0, z0], [x1, y1, z1]], got {rows!r}")
        fixed_box = [_numbers(row, "fixed_box", "boundary", path, 3) for row in rows]
        fixed = vertices_in_box(mesh.vertices, fixed_box)
        if len(fixed) == 0:
            raise ValueError(f"{path}: [boundary] fixed_box {fixed_box} contains no mesh vertex")
    elif "fixed_vertices" in b:
        fpath = base / _text(b["fixed_vertices"], "fixed_vertices", "boundary", path)
        if not fpath.exists():
            raise FileNotFoundError(f"{path}: fixed_vertices file not found: {fpath}")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # numpy's "input contained no data": named below
                fixed = np.atleast_1d(np.loadtxt(fpath, dtype=np.int64, comments="#"))
        except ValueError as err:
            raise ValueError(f"{path}: fixed_vertices file {fpath}: expected one integer vertex "
                             f"index per line ({err})") from None
        if len(fixed) == 0:  # as a fixed_box with no vertex in it
            raise ValueError(f"{path}: fixed_vertices file {fpath} lists no vertex (for a free body, "
                             "leave out [boundary])")
        bad = fixed[(fixed < 0) | (fixed >= mesh.num_vertices)]
        if len(bad):
            raise ValueError(f"{path}: fixed_vertices file {fpath}: vertex index {int(bad[0])} is out "
                             f"of range; the mesh has {mesh.num_vertices} vertices (0-based indices "
                             f"0..{mesh.num_vertices - 1})")
    elif b:
        raise ValueError(f"{path}: [boundary] needs fixed_box or fixed_vertices")
    else:
        fixed = np.zeros(0, np.int64)
    weak = clamp_weakness(mesh.vertices, fixed)
    if weak:
        warnings.warn(f"{path}: [boundary] {weak}", stacklevel=2)

    s = doc["simulation"]
    time_step = _number(_require(s, "time_step", "simulation", path), "time_step", "simulation", path)
    gravity = tuple(_numbers(s.get("gravity", DEFAULT_GRAVITY), "gravity", "simulation", path, 3))

    recs = []
    if not isinstance(doc.get("recording", []), list):
        raise ValueError(f"{path}: recordings are an array of tables: write [[recording]], not [recording]")
    for i, r in enumerate(doc.get("recording", [])):
        if "file" not in r:
            raise ValueError(f"{path}: [[recording]] #{i} has no 'file'")
        rp = base / _text(r["file"], "file", "recording", path)
        if not rp.exists():
            raise FileNotFoundError(f"{path}: recording file not found: {rp}")
        role = r.get("role", "train")
        if role not in ROLES:
            raise ValueError(f"{path}: [[recording]] #{i} ({r['file']}): role must be one of {ROLES}, "
                             f"got {role!r}{_did_you_mean(str(role), ROLES)}")
        recs.append((rp, role))
    return Scene(
        mesh=mesh,
        material=material,
        damping=damping,
        fixed=fixed,
        time_step=time_step,
        gravity=gravity,
        recordings=recs,
        path=path,
        fixed_box=fixed_box,
        mesh_file=mesh_file,
        mesh_options=opts,
    )


def _fmt(x) -> str:
    if isinstance(x, str):
        return '"' + x.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt(v) for v in x) + "]"
    return repr(float(x))


def _rel(p: Path, base: Path) -> str:
    p = Path(p).resolve()
    try:
        return p.relative_to(base.resolve()).as_posix()
    except ValueError:
        return p.as_posix()


def save_scene(scene: Scene, path, mesh_file: str | None = None) -> Path:
    """Write `scene` as `path` (scene.toml) in the formats.md layout. The mesh is written with
    meshio to `mesh_file` (relative to the scene; default "mesh.vtu"; .vtu or .msh). Without a
    fixed_box the clamp is written to "fixed.txt" (fixed_vertices). Recording paths are written
    relative to the scene file when possible; the files themselves are not copied."""
    path = Path(path)
    base = path.parent
    base.mkdir(parents=True, exist_ok=True)
    mesh_file = mesh_file or "mesh.vtu"
    if Path(mesh_file).suffix.lower() not in (".vtu", ".msh", ".vtk"):
        raise ValueError(f"mesh_file: write .vtu, .msh or .vtk, got {mesh_file}")
    meshes.save_mesh(scene.mesh, base / mesh_file)
    mat, dmp = scene.material, scene.damping
    for name in ("youngs_modulus", "poisson_ratio", "density"):
        if np.ndim(getattr(mat, name)) != 0:
            raise ValueError(f"save_scene: scene.toml holds a scalar {name}; got a per-tet array")
    lines = ["[mesh]", f"file = {_fmt(mesh_file)}", ""]
    lines += [
        "[material]",
        f"model = {_fmt(mat.model)}",
        f"youngs_modulus = {_fmt(mat.youngs_modulus)}",
        f"poisson_ratio = {_fmt(mat.poisson_ratio)}",
        f"density = {_fmt(mat.density)}",
    ]
    if mat.edits:
        lines.append(f"edits = {_fmt([list(e) for e in mat.edits])}")
    lines += [
        "",
        "[damping]",
        f"alpha_mass = {_fmt(dmp.alpha_mass)}",
        f"alpha_stiffness = {_fmt(dmp.alpha_stiffness)}",
    ]
    if dmp.mass_poly:
        lines.append(f"mass_poly = {_fmt(dmp.mass_poly)}")
    if dmp.stiffness_poly:
        lines.append(f"stiffness_poly = {_fmt(dmp.stiffness_poly)}")
    lines.append("")
    if scene.fixed_box is not None:
        lines += ["[boundary]", f"fixed_box = {_fmt([list(r) for r in scene.fixed_box])}", ""]
    elif len(scene.fixed):
        np.savetxt(base / "fixed.txt", scene.fixed, fmt="%d")
        lines += ["[boundary]", 'fixed_vertices = "fixed.txt"', ""]
    lines += [
        "[simulation]",
        f"time_step = {_fmt(scene.time_step)}",
        f"gravity = {_fmt(list(scene.gravity))}",
        "",
    ]
    for rp, role in scene.recordings:
        lines += ["[[recording]]", f"file = {_fmt(_rel(rp, base))}", f"role = {_fmt(role)}", ""]
    path.write_text("\n".join(lines))
    return path
