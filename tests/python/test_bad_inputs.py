"""Bad input raises a clear Python error naming the problem (ValueError for bad values/shapes,
FileNotFoundError for missing files); numerical failure in C++ raises RuntimeError naming the
step, never a crash or silent NaN."""
import numpy as np
import pytest

from matlearn import _core, meshes
from matlearn.materials import Material, make_model

fem = _core.fem


def cube():
    V, T = meshes.grid_tets((1, 1, 1), (1.0, 1.0, 1.0))
    return V, T


def good_model():
    mesh = meshes.bar(cells=(4, 1, 1))
    return mesh, make_model(mesh, Material("corotated", 1e5, 0.4, 1000.0))


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda V, T: (V[:, :2], T), r"vertices: expected shape \(N, 3\)"),
        (lambda V, T: (V, T[:, :3]), r"tets: expected shape \(N, 4\)"),
        (lambda V, T: (V, T.astype(float)), "tets: expected an integer array"),
        (lambda V, T: (np.where(np.arange(V.size).reshape(V.shape) == 4, np.nan, V), T), "NaN"),
        (lambda V, T: (V, np.where(T == T.max(), 99, T)), r"must lie in \[0, 8\)"),
        (lambda V, T: (V, np.where(T == 0, -1, T)), r"must lie in \[0, 8\)"),
        (lambda V, T: (V, T[:, [0, 2, 1, 3]]), "inverted"),
        (lambda V, T: (np.vstack([V, V[:3].mean(0) + [0, 0, 0], V[1]]), np.vstack([T, [0, 1, 8, 9]])), "degenerate"),
    ],
    ids=["vertices-2d", "tets-3-cols", "float-tets", "nan", "index-too-large", "negative-index",
         "inverted", "degenerate"],
)
def test_bad_meshes(mutate, match):
    V, T = cube()
    V2, T2 = mutate(V.copy(), T.copy())
    with pytest.raises(ValueError, match=match):
        fem.TetMesh(V2, T2)


def test_bad_model_parameters():
    mesh = meshes.bar(cells=(2, 1, 1))
    m = mesh.num_tets
    one = np.ones(m)
    with pytest.raises(ValueError, match=r"mu: expected shape \(12\)"):
        fem.Model(mesh, "corotated", np.ones(m + 1), one, one)
    with pytest.raises(ValueError, match="shear modulus"):
        fem.Model(mesh, "corotated", -one, one, one)
    with pytest.raises(ValueError, match="Poisson"):
        fem.Model(mesh, "corotated", one, -one, one)
    with pytest.raises(ValueError, match="density"):
        fem.Model(mesh, "corotated", one, one, 0 * one)
    with pytest.raises(ValueError, match="unknown material model"):
        fem.Model(mesh, "rubber", one, one, one)
    with pytest.raises(ValueError, match="poisson_ratio"):
        Material("corotated", 1e5, 0.5)


def test_bad_states():
    mesh, model = good_model()
    X = mesh.vertices
    v = np.zeros_like(X)
    with pytest.raises(ValueError, match=r"x: expected shape \(\d+, 3\), got \(3, 3\)"):
        model.forces(X[:3], v)
    bad = X.copy()
    bad[2, 1] = np.inf
    with pytest.raises(ValueError, match="x contains NaN or Inf"):
        model.forces(bad, v)
    with pytest.raises(ValueError, match="v contains NaN"):
        model.stiffness(X, np.full_like(X, np.nan))


def test_bad_integrator_inputs():
    mesh, model = good_model()
    X = mesh.vertices
    n = len(X)
    fixed = np.where(X[:, 0] < 1e-9)[0]
    g = np.zeros(3)
    with pytest.raises(ValueError, match="fixed vertex index out of range"):
        _core.time.Integrator(model, np.array([n]), 1e-3, g)
    with pytest.raises(ValueError, match="time_step"):
        _core.time.Integrator(model, fixed, -1e-3, g)
    with pytest.raises(ValueError, match="fixed: expected an integer array"):
        _core.time.Integrator(model, fixed.astype(float) + 0.5, 1e-3, g)
    integ = _core.time.Integrator(model, fixed, 1e-3, g)
    with pytest.raises(ValueError, match="f_ext: expected shape"):
        integ.step(np.zeros((n + 1, 3)))
    with pytest.raises(ValueError, match="x contains NaN"):
        integ.set_state(np.full_like(X, np.nan), np.zeros_like(X))
    free = _core.time.Integrator(model, np.zeros(0, np.int64), 1e-3, g)
    with pytest.raises(ValueError, match="needs fixed vertices"):
        free.static_solve(np.zeros_like(X))
    integ.set_prescribed(np.array([n - 1]))
    with pytest.raises(ValueError, match="targets"):
        integ.step(np.zeros_like(X))
    with pytest.raises(ValueError, match="targets: expected shape"):
        integ.simulate_constrained(np.zeros((3, 2, 3)), np.zeros_like(X))


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.msh"):
        meshes.load_mesh(tmp_path / "nope.msh")
    (tmp_path / "only.node").write_text("4 3 0 0\n0 0 0 0\n1 1 0 0\n2 0 1 0\n3 0 0 1\n")
    with pytest.raises(FileNotFoundError, match="only.ele"):
        meshes.load_mesh(tmp_path / "only.node")
    (tmp_path / "mesh.xyz").write_text("")
    with pytest.raises(ValueError, match="unsupported mesh format"):
        meshes.load_mesh(tmp_path / "mesh.xyz")


def open_box():
    import trimesh

    box = trimesh.creation.box()
    return box.vertices, box.faces[:-2]  # one square side missing


def test_non_closed_surface(tmp_path):
    import trimesh

    V, F = open_box()
    path = tmp_path / "open.obj"
    trimesh.Trimesh(V, F, process=False).export(path)
    with pytest.raises(ValueError, match="not closed"):
        meshes.load_mesh(path)
    # Straight into TetGen (no trimesh check in front): still a ValueError, no crash.
    with pytest.raises(ValueError, match="TetGen|closed"):
        meshes.tetrahedralize(V, F, max_volume=0.1)


def test_numerical_failure_names_the_step():
    mesh, model = good_model()
    X = mesh.vertices
    fixed = np.where(X[:, 0] < 1e-9)[0]

    def exploding(Fh, Fhdot):
        # A strongly destabilising correction (negative stiffness 1000x the material's).
        k = -1e8
        return k * (Fh - 1.0), np.broadcast_to(k * np.eye(3), (len(Fh), 3, 3)).copy(), None, None

    model.correction = _core.correction.PythonCorrection(exploding)
    integ = _core.time.Integrator(model, fixed, 0.5, np.array([0.0, 0.0, -9.81]))
    with pytest.raises(RuntimeError, match=r"step \d+"):
        for _ in range(50):
            integ.step(np.zeros_like(X))

    def nan_after_a_while(Fh, Fhdot):
        bad = np.abs(Fh - 1).max() > 1e-4
        return np.full_like(Fh, np.nan if bad else 0.0), None, None, None

    model.correction = _core.correction.PythonCorrection(nan_after_a_while)
    integ = _core.time.Integrator(model, fixed, 1e-2, np.array([0.0, 0.0, -9.81]))
    with pytest.raises(RuntimeError, match=r"step \d+, Newton iteration \d+: correction returned NaN"):
        for _ in range(50):
            integ.step(np.zeros_like(X))


def test_correction_with_wrong_output_shape_is_a_value_error():
    mesh, model = good_model()
    model.correction = _core.correction.PythonCorrection(lambda Fh, Fhdot: (np.zeros((2, 3)), None, None, None))
    with pytest.raises(ValueError, match="correction dPh: expected shape"):
        model.forces(mesh.vertices, np.zeros_like(mesh.vertices))


def test_markers_only_on_the_clamp_are_named():
    """Markers whose nearest vertices are all clamped (markers on the clamp, or in other units
    than a mesh whose clamp holds its origin) leave nothing to follow: a clear error instead of
    the integrator's internal 'call set_prescribed() first'."""
    from matlearn.learning.initial import initial_trajectory
    from matlearn.recording import Recording
    from matlearn.scene import Scene, vertices_in_box

    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(4, 1, 1))
    box = [[-1, -1, -1], [1e-3, 1, 1]]
    scene = Scene(mesh, Material("corotated", 1e5, 0.4, 1000.0), fixed=vertices_in_box(mesh.vertices, box),
                  fixed_box=box)
    rest = np.asarray(mesh.vertices)[scene.fixed[:3]]
    rec = Recording([0.0, 0.01], rest, np.stack([rest, rest]), at_rest_initially=True)
    with pytest.raises(ValueError, match="every marker's nearest mesh vertex is clamped"):
        initial_trajectory(scene, scene.model(), rec)
