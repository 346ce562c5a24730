"""scene.toml (docs/formats.md): the documented example parses exactly; roundtrip; clear errors."""
import textwrap
import warnings

import meshio
import numpy as np
import pytest

from matlearn import meshes
from matlearn.recording import Recording, save_recording
from matlearn.scene import Scene, load_scene, save_scene, vertices_in_box

FORMATS_EXAMPLE = textwrap.dedent(
    """\
    [mesh]
    file = "bar.msh"          # tetrahedral mesh (.msh, .vtk, .vtu, TetGen .node/.ele) or a closed
                              # surface (.obj, .ply, .stl, .off) to tetrahedralise with TetGen
    max_volume = 1e-6         # optional, TetGen volume bound for surfaces (m^3)
    min_ratio = 1.4           # optional, TetGen radius-edge quality bound

    [material]                # the nominal model
    model = "corotated"       # also: "neo_hookean", "stvk"
    youngs_modulus = 1.0e5    # Pa
    poisson_ratio = 0.40
    density = 1000.0          # kg/m^3

    [damping]                 # Rayleigh: damping force = -(alpha_mass M + alpha_stiffness K) v
    alpha_mass = 0.0          # 1/s
    alpha_stiffness = 0.01    # s

    [boundary]
    fixed_box = [[-1.0, -1.0, -1.0], [0.001, 1.0, 1.0]]   # rest-space box: vertices inside are clamped
    # or: fixed_vertices = "fixed.txt"  (one 0-based vertex index per line)

    [simulation]
    time_step = 0.001         # s
    gravity = [0.0, -9.81, 0.0]

    [[recording]]
    file = "train_0.npz"
    role = "train"            # "train" recordings are learned from; "test" ones only scored
    [[recording]]
    file = "test_0.npz"
    role = "test"
    """
)


def _recording(path, mesh):
    rest = mesh.vertices[:3]
    save_recording(Recording([0.0, 0.01], rest, np.stack([rest, rest]), at_rest_initially=True), path)


@pytest.fixture
def example_dir(tmp_path):
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(4, 1, 1))
    meshio.write(tmp_path / "bar.msh", meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]), file_format="gmsh")
    _recording(tmp_path / "train_0.npz", mesh)
    _recording(tmp_path / "test_0.npz", mesh)
    (tmp_path / "scene.toml").write_text(FORMATS_EXAMPLE)
    return tmp_path, mesh


def test_formats_example_parses_exactly(example_dir):
    d, mesh = example_dir
    sc = load_scene(d / "scene.toml")
    np.testing.assert_allclose(sc.mesh.vertices, mesh.vertices)
    np.testing.assert_array_equal(sc.mesh.tets, mesh.tets)
    m = sc.material
    assert (m.model, m.youngs_modulus, m.poisson_ratio, m.density) == ("corotated", 1e5, 0.4, 1000.0)
    assert (sc.damping.alpha_mass, sc.damping.alpha_stiffness) == (0.0, 0.01)
    np.testing.assert_array_equal(sc.fixed, np.flatnonzero(mesh.vertices[:, 0] <= 0.001))
    assert len(sc.fixed) == 4
    assert sc.time_step == 0.001 and sc.gravity == (0.0, -9.81, 0.0)
    assert sc.recordings == [(d / "train_0.npz", "train"), (d / "test_0.npz", "test")]
    assert len(sc.recordings_with_role("train")) == 1 and len(sc.recordings_with_role("test")) == 1
    assert sc.object_size == pytest.approx(np.sqrt(0.2**2 + 2 * 0.04**2))
    assert sc.mesh_options == {"max_volume": 1e-6, "min_ratio": 1.4}
    integ = sc.integrator()
    np.testing.assert_array_equal(np.sort(integ.fixed), sc.fixed)
    assert integ.time_step == 0.001


def test_relative_paths_are_relative_to_the_scene_file(example_dir, monkeypatch, tmp_path_factory):
    d, _ = example_dir
    monkeypatch.chdir(tmp_path_factory.mktemp("elsewhere"))
    assert load_scene(d / "scene.toml").recordings[0][0] == d / "train_0.npz"


def test_roundtrip(example_dir, tmp_path_factory):
    d, _ = example_dir
    sc = load_scene(d / "scene.toml")
    sc.damping.stiffness_poly = [0.5, -0.1]
    out = tmp_path_factory.mktemp("out")
    for mesh_file in ("m.vtu", "m.msh"):
        back = load_scene(save_scene(sc, out / "scene.toml", mesh_file=mesh_file))
        np.testing.assert_allclose(back.mesh.vertices, sc.mesh.vertices)
        np.testing.assert_array_equal(back.mesh.tets, sc.mesh.tets)
        np.testing.assert_array_equal(back.fixed, sc.fixed)
        assert back.material == sc.material and back.damping == sc.damping
        assert back.gravity == sc.gravity and back.time_step == sc.time_step
        assert back.recordings == sc.recordings and back.fixed_box == sc.fixed_box


def test_fixed_vertices_file(example_dir):
    d, mesh = example_dir
    (d / "fixed.txt").write_text("0\n3\n7\n")
    text = FORMATS_EXAMPLE.replace(
        "fixed_box = [[-1.0, -1.0, -1.0], [0.001, 1.0, 1.0]]", 'fixed_vertices = "fixed.txt"'
    )
    (d / "scene.toml").write_text(text)
    sc = load_scene(d / "scene.toml")
    np.testing.assert_array_equal(sc.fixed, [0, 3, 7])
    # Without a box the clamp is saved as a vertex list.
    back = load_scene(save_scene(sc, d / "copy" / "scene.toml"))
    np.testing.assert_array_equal(back.fixed, [0, 3, 7])
    # an empty file clamped nothing, with only numpy's warning (a box with no vertex is an error)
    (d / "fixed.txt").write_text("# no vertex\n")
    with pytest.raises(ValueError, match="fixed.txt lists no vertex"), warnings.catch_warnings():
        warnings.simplefilter("error")  # and no numpy warning on the way
        load_scene(d / "scene.toml")


@pytest.mark.parametrize(
    "old, new, err, match",
    [
        ('file = "bar.msh"', 'file = "missing.msh"', FileNotFoundError, "missing.msh"),
        ('file = "test_0.npz"', 'file = "gone.npz"', FileNotFoundError, "gone.npz"),
        ("youngs_modulus = 1.0e5    # Pa\n", "", ValueError, "youngs_modulus"),
        ("time_step = 0.001", "dt = 0.001", ValueError, "time_step"),
        ("[-1.0, -1.0, -1.0], [0.001, 1.0, 1.0]", "[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]", ValueError, "no mesh vertex"),
        ('model = "corotated"', 'model = "rubber"', ValueError, "unknown material model"),
        ('role = "test"', 'role = "validation"', ValueError, "role"),
        ("[simulation]", "[simulationx]", ValueError, r"\[simulation\]"),
        ("gravity = [0.0, -9.81, 0.0]", "gravity = [0.0, -9.81]", ValueError, "gravity"),
        ("density = 1000.0 ", "density = 1000.0 = ", ValueError, "invalid TOML"),
    ],
)
def test_errors(example_dir, old, new, err, match):
    d, _ = example_dir
    assert old in FORMATS_EXAMPLE
    (d / "scene.toml").write_text(FORMATS_EXAMPLE.replace(old, new))
    with pytest.raises(err, match=match):
        load_scene(d / "scene.toml")


def test_missing_scene_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="scene file not found"):
        load_scene(tmp_path / "scene.toml")


def test_vertices_in_box():
    V = np.array([[0.0, 0, 0], [1, 1, 1], [0.5, 2, 0]])
    np.testing.assert_array_equal(vertices_in_box(V, [[1, 1, 1], [0, 0, 0]]), [0, 1])
    with pytest.raises(ValueError, match="box"):
        vertices_in_box(V, [0, 0, 0, 1, 1, 1])


def test_scene_validation():
    m = meshes.bar(cells=(1, 1, 1))
    from matlearn.materials import Material

    with pytest.raises(ValueError, match="time_step"):
        Scene(m, Material(), time_step=0.0)
    with pytest.raises(ValueError, match="out of range"):
        Scene(m, Material(), fixed=[100])


def test_surface_mesh_is_tetrahedralised_with_the_scene_bounds(tmp_path):
    import trimesh

    trimesh.creation.box(extents=(0.1, 0.02, 0.02)).export(tmp_path / "box.obj")
    text = (
        '[mesh]\nfile = "box.obj"\nmax_volume = 2e-7\nmin_ratio = 1.5\n'
        '[material]\nmodel = "neo_hookean"\nyoungs_modulus = 2e5\npoisson_ratio = 0.3\ndensity = 900.0\n'
        "[boundary]\nfixed_box = [[-1, -1, -1], [-0.049, 1, 1]]\n[simulation]\ntime_step = 0.002\n"
    )
    (tmp_path / "scene.toml").write_text(text)
    sc = load_scene(tmp_path / "scene.toml")
    assert sc.mesh.rest_volumes.max() <= 2e-7 * (1 + 1e-9)
    assert sc.mesh.rest_volumes.sum() == pytest.approx(0.1 * 0.02 * 0.02, rel=1e-9)
    assert sc.gravity == (0.0, -9.81, 0.0) and sc.damping.alpha_stiffness == 0.0 and len(sc.fixed) >= 4


@pytest.mark.parametrize("bounds, match", [
    ("min_ratio = 1.0", r"box.obj: min_ratio must be at least 1.1"),  # TetGen refined without end
    ("min_ratio = 0.5", r"box.obj: min_ratio must be at least 1.1"),
    ("max_volume = 0.0", r"box.obj: max_volume must be a positive volume"),  # was silently no bound
    ("max_volume = -1.0", r"box.obj: max_volume must be a positive volume"),
    ("max_volume = 1e-12", r"box.obj: max_volume = 1e-12 m\^3 would make at least 4e\+07 tets"),  # mm^3 for m^3
])
def test_surface_bounds_tetgen_cannot_meet_are_named(tmp_path, bounds, match):
    import trimesh

    trimesh.creation.box(extents=(0.1, 0.02, 0.02)).export(tmp_path / "box.obj")
    text = (
        f'[mesh]\nfile = "box.obj"\n{bounds}\n'
        '[material]\nmodel = "corotated"\nyoungs_modulus = 2e5\npoisson_ratio = 0.3\ndensity = 900.0\n'
        "[simulation]\ntime_step = 0.002\n"
    )
    (tmp_path / "scene.toml").write_text(text)
    with pytest.raises(ValueError, match=match):
        load_scene(tmp_path / "scene.toml")


def test_tetgen_bounds_are_checked_in_the_core_too():
    import trimesh

    box = trimesh.creation.box(extents=(0.1, 0.02, 0.02))
    with pytest.raises(ValueError, match="min_ratio .* must be at least 1.1"):
        meshes.tetrahedralize(box.vertices, box.faces, 1e-6, 1.0)
    assert meshes.tetrahedralize(box.vertices, box.faces, 1e-6, meshes.MIN_RADIUS_EDGE_RATIO).num_tets > 0


def test_a_clamp_that_cannot_hold_the_body_warns(example_dir):
    """A clamp of 1-2 vertices, or of vertices on one line, leaves a rigid rotation free: loading
    the scene says so (static solves would fail later with a CHOLMOD message); the example's
    clamped end face does not warn."""
    import warnings

    from matlearn.scene import clamp_weakness

    d, mesh = example_dir
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sc = load_scene(d / "scene.toml")
    assert len(sc.fixed) >= 3 and clamp_weakness(mesh.vertices, sc.fixed) is None
    V = np.asarray(mesh.vertices)
    edge = np.flatnonzero(np.isclose(V[:, 1], V[:, 1].min()) & np.isclose(V[:, 2], V[:, 2].min()))
    assert len(edge) >= 3
    assert "one line" in clamp_weakness(V, edge)
    assert "only 2" in clamp_weakness(V, edge[:2])
    assert clamp_weakness(V, []) is None  # nothing clamped: a free or drive-held body
    (d / "fixed.txt").write_text("0\n")
    (d / "scene.toml").write_text(FORMATS_EXAMPLE.replace(
        "fixed_box = [[-1.0, -1.0, -1.0], [0.001, 1.0, 1.0]]", 'fixed_vertices = "fixed.txt"'))
    with pytest.warns(UserWarning, match="clamps only 1 vertex"):
        load_scene(d / "scene.toml")


@pytest.mark.parametrize(
    "old, new, match",
    [
        ("[damping]", "[dampng]", r"unknown section 'dampng' ignored \(did you mean 'damping'\?\)"),
        ("alpha_stiffness = 0.01", "alpha_stifness = 0.01",
         r"unknown key 'alpha_stifness' in \[damping\] ignored \(did you mean 'alpha_stiffness'\?\)"),
        ("gravity = [0.0, -9.81, 0.0]", "gravty = [0.0, -9.81, 0.0]", r"did you mean 'gravity'"),
        ('role = "test"', 'rol = "test"', r"unknown key 'rol' in \[recording\]"),
    ],
)
def test_misspelt_keys_and_sections_are_reported(example_dir, old, new, match):
    """A misspelt optional key silently keeps its default (no damping, the default gravity, a
    test recording learned from as train): loading the scene says so, naming the closest key."""
    d, _ = example_dir
    (d / "scene.toml").write_text(FORMATS_EXAMPLE.replace(old, new))
    with pytest.warns(UserWarning, match=match):
        load_scene(d / "scene.toml")


@pytest.mark.parametrize(
    "old, new, match",
    [
        ("youngs_modulus = 1.0e5", 'youngs_modulus = "abc"', r"\[material\] youngs_modulus must be a number, got the string 'abc'"),
        ("youngs_modulus = 1.0e5", 'youngs_modulus = "1e5"', r"youngs_modulus must be a number, got the string '1e5' \(write it without quotes\)"),
        ("youngs_modulus = 1.0e5", "youngs_modulus = -1.0e5", r"youngs_modulus must be > 0 \(Pa\), got -100000.0"),
        ("alpha_mass = 0.0", "alpha_mass = -1.0", "alpha_mass -1.0"),
        ("time_step = 0.001", "time_step = true", r"\[simulation\] time_step must be a number"),
        ('role = "test"', 'role = "tset"', r"role must be one of \('train', 'test'\), got 'tset' \(did you mean 'test'\?\)"),
        ("youngs_modulus = 1.0e5    # Pa\n", "young_modulus = 1.0e5\n", r"missing key 'youngs_modulus' in \[material\] \(did you mean 'young_modulus'\?\)"),
    ],
)
def test_bad_values_name_their_key(example_dir, old, new, match):
    d, _ = example_dir
    (d / "scene.toml").write_text(FORMATS_EXAMPLE.replace(old, new))
    with pytest.raises(ValueError, match=match), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the misspelt key's own warning
        load_scene(d / "scene.toml")


def test_fixed_vertex_out_of_range_is_named(example_dir):
    d, mesh = example_dir
    (d / "fixed.txt").write_text("0\n500\n")
    (d / "scene.toml").write_text(FORMATS_EXAMPLE.replace(
        "fixed_box = [[-1.0, -1.0, -1.0], [0.001, 1.0, 1.0]]", 'fixed_vertices = "fixed.txt"'))
    with pytest.raises(ValueError, match=rf"vertex index 500 is out of range; the mesh has {mesh.num_vertices}"):
        load_scene(d / "scene.toml")


def test_markers_in_other_units_are_named(example_dir):
    """Markers whose rest positions lie off the mesh, or that a clamped body would have to travel
    far beyond its size to reach (markers in mm, marker_rest in m), stop with an error naming the
    recording and the likely cause instead of a failed static solve or a silent wrong fit."""
    d, mesh = example_dir
    sc = load_scene(d / "scene.toml")
    rest = np.asarray(mesh.vertices)[[5, 6, 7]]
    near = Recording([0.0, 0.01], rest, np.stack([rest, rest + 1e-3]))
    sc.check_recording(near, "ok")  # a millimetre of motion on a 0.2 m bar
    with pytest.raises(ValueError, match=r"mm: marker 0's rest position .* lies .* from the model's mesh"):
        sc.check_recording(Recording([0.0, 0.01], 1e3 * rest, np.stack([1e3 * rest] * 2)), "mm")
    with pytest.raises(ValueError, match=r"mixed: marker \d is seen .* from its rest position .* same units"):
        sc.check_recording(Recording([0.0, 0.01], rest, np.stack([rest, 1e3 * rest])), "mixed")
    # markers in m on a mesh in mm (here: the markers shrunk 1000x) sit near the mesh but span
    # a thousandth of it: a warning (a few markers on one small patch are legitimate)
    tiny = 1e-3 * np.asarray(mesh.vertices)[:6]
    with pytest.warns(UserWarning, match=r"6 markers span .* less than the object .* same units"):
        sc.check_recording(Recording([0.0, 0.01], tiny, np.stack([tiny, tiny])), "tiny")
    with pytest.warns(UserWarning, match=r"frames are 10 s apart \(median\): are its times in seconds\? "
                                         rf"\(its 20 s take {20 / sc.time_step:,.0f} time steps"):
        sc.check_recording(Recording([0.0, 10.0, 20.0], rest, np.stack([rest] * 3)), "ms")  # 10 ms frames as s
    # a marker never seen carries nothing: said, with its index
    blind = np.stack([rest, rest + 1e-3])
    blind[:, 1] = np.nan
    with pytest.warns(UserWarning, match=r"blind: marker\(s\) \[1\] \(1 of 3\) never seen"):
        sc.check_recording(Recording([0.0, 0.01], rest, blind), "blind")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a long recording at a high frame rate is fine
        sc.check_recording(Recording(np.arange(0.0, 300.0, 0.01), rest, np.repeat(rest[None], 30000, axis=0)), "long")
    save_recording(Recording([0.0, 0.01], rest, np.stack([rest, 1e3 * rest])), d / "train_0.npz")
    with pytest.raises(ValueError, match="train recording train_0.npz: marker"):
        sc.recordings_with_role("train")


@pytest.mark.parametrize(
    "old, new, match",
    [
        ("[[recording]]\nfile = \"train_0.npz\"", "[recording]\nfile = \"train_0.npz\"", r"write \[\[recording\]\]"),
        ("fixed_box = [[-1.0, -1.0, -1.0], [0.001, 1.0, 1.0]]", "fixed_box = [1, 2]", "fixed_box must be"),
        ("fixed_box = [[-1.0, -1.0, -1.0], [0.001, 1.0, 1.0]]", "fixed_vertices = 5", "fixed_vertices must be a file name"),
        ('file = "bar.msh"', "file = 5", r"\[mesh\] file must be a file name"),
        ("youngs_modulus = 1.0e5", "youngs_modulus = nan", "youngs_modulus must be a finite number"),
    ],
)
def test_malformed_tables_and_values_are_named(example_dir, old, new, match):
    """Shapes TOML allows but the scene does not: each a ValueError naming the key (these were
    TypeErrors, tracebacks on the command line, or a NaN modulus loaded silently)."""
    d, _ = example_dir
    text = FORMATS_EXAMPLE.replace(old, new, 1)
    if "[recording]" in new:  # every recording then a single table
        text = text.replace("[[recording]]\nfile = \"test_0.npz\"\nrole = \"test\"\n", "")
    assert text != FORMATS_EXAMPLE
    (d / "scene.toml").write_text(text)
    with pytest.raises(ValueError, match=match), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        load_scene(d / "scene.toml")
