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
        return [load_recording(p) for p in self.recording_paths(role)]


def _require(table: dict, key: str, where: str, path: Path):
    if key not in table:
        raise ValueError(f"{path}: missing key '{key}' in [{where}]")
    return table[key]


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
    for section in ("mesh", "material", "simulation"):
        if section not in doc:
            raise ValueError(f"{path}: missing section [{section}]")

    m = doc["mesh"]
    mesh_file = base / _require(m, "file", "mesh", path)
    opts = {k: float(m[k]) for k in ("max_volume", "min_ratio") if k in m}
    mesh = meshes.load_mesh(mesh_file, **opts)

    mat = doc["material"]
    material = Material(
        model=_require(mat, "model", "material", path),
        youngs_modulus=float(_require(mat, "youngs_modulus", "material", path)),
        poisson_ratio=float(_require(mat, "poisson_ratio", "material", path)),
        density=float(_require(mat, "density", "material", path)),
        edits=[tuple(e) for e in mat.get("edits", [])],
    )
    d = doc.get("damping", {})
    damping = Damping(
        alpha_mass=float(d.get("alpha_mass", 0.0)),
        alpha_stiffness=float(d.get("alpha_stiffness", 0.0)),
        mass_poly=[float(c) for c in d.get("mass_poly", [])],
        stiffness_poly=[float(c) for c in d.get("stiffness_poly", [])],
    )

    b = doc.get("boundary", {})
    fixed_box = None
    if "fixed_box" in b and "fixed_vertices" in b:
        raise ValueError(f"{path}: [boundary] has both fixed_box and fixed_vertices; give one")
    if "fixed_box" in b:
        fixed_box = [[float(x) for x in row] for row in b["fixed_box"]]
        fixed = vertices_in_box(mesh.vertices, fixed_box)
        if len(fixed) == 0:
            raise ValueError(f"{path}: [boundary] fixed_box {fixed_box} contains no mesh vertex")
    elif "fixed_vertices" in b:
        fpath = base / b["fixed_vertices"]
        if not fpath.exists():
            raise FileNotFoundError(f"{path}: fixed_vertices file not found: {fpath}")
        fixed = np.atleast_1d(np.loadtxt(fpath, dtype=np.int64, comments="#"))
    elif b:
        raise ValueError(f"{path}: [boundary] needs fixed_box or fixed_vertices")
    else:
        fixed = np.zeros(0, np.int64)
    weak = clamp_weakness(mesh.vertices, fixed)
    if weak:
        warnings.warn(f"{path}: [boundary] {weak}", stacklevel=2)

    s = doc["simulation"]
    time_step = float(_require(s, "time_step", "simulation", path))
    gravity = tuple(float(x) for x in s.get("gravity", DEFAULT_GRAVITY))

    recs = []
    for i, r in enumerate(doc.get("recording", [])):
        if "file" not in r:
            raise ValueError(f"{path}: [[recording]] #{i} has no 'file'")
        rp = base / r["file"]
        if not rp.exists():
            raise FileNotFoundError(f"{path}: recording file not found: {rp}")
        recs.append((rp, r.get("role", "train")))
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
