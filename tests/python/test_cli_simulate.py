"""`matlearn simulate` end to end on a tiny bar: recording, VTU series, markers, errors."""
import meshio
import numpy as np
import pytest

from matlearn import cli, meshes
from matlearn.materials import Damping, Material
from matlearn.recording import Recording, load_recording, save_recording
from matlearn.scene import Scene, save_scene, vertices_in_box

CLAMP = [[-1, -1, -1], [1e-3, 1, 1]]
TIP_BOX = ["0.199", "-1", "-1", "1", "1", "1"]


@pytest.fixture
def scene_path(tmp_path):
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(5, 1, 1))
    scene = Scene(mesh, Material(youngs_modulus=2e5), Damping(alpha_stiffness=0.005),
                  vertices_in_box(mesh.vertices, CLAMP), 1e-3, fixed_box=CLAMP)
    return save_scene(scene, tmp_path / "scene.toml"), scene


def test_release_writes_recording_and_vtu(scene_path, tmp_path, capsys):
    path, scene = scene_path
    out, vtu = tmp_path / "rec.npz", tmp_path / "vtu"
    rc = cli.main(["simulate", str(path), "--load", "0", "0.4", "0", "--load-box", *TIP_BOX,
                   "--release", "--duration", "0.05", "--frame-rate", "200", "--all-surface",
                   "--out", str(out), "--vtu", str(vtu)])
    assert rc == 0
    rec = load_recording(out)
    np.testing.assert_allclose(rec.times, np.arange(11) / 200.0, atol=1e-12)
    assert not rec.at_rest_initially
    mesh = scene.mesh
    np.testing.assert_allclose(rec.marker_rest, mesh.vertices[meshes.surface_vertices(mesh)])
    # Frame 0 is the static equilibrium under the tip load (computed independently here).
    model, integ = scene.model(), scene.integrator()
    n = mesh.num_vertices
    tip = vertices_in_box(mesh.vertices, [[0.199, -1, -1], [1, 1, 1]])
    f = np.zeros((n, 3))
    f[tip, 1] = 0.4 * model.vertex_mass[tip] / model.vertex_mass[tip].sum()
    integ.static_solve(f, load_steps=5)
    np.testing.assert_allclose(rec.markers[0], np.asarray(integ.x)[meshes.surface_vertices(mesh)], atol=1e-8)
    assert rec.markers[0, :, 1].max() > 0.001  # held up by the load, then released
    # The ParaView series: a .pvd listing every frame, each .vtu holding the deformed mesh.
    pvd = (vtu / "frame.pvd").read_text()
    assert pvd.count("<DataSet") == 11 and 'timestep="0.05"' in pvd
    last = meshio.read(vtu / "frame_00010.vtu")
    np.testing.assert_allclose(last.points, rec.markers[-1], atol=1e-10)  # every vertex is a marker
    np.testing.assert_allclose(last.point_data["displacement"], rec.markers[-1] - mesh.vertices, atol=1e-10)
    assert "wrote" in capsys.readouterr().out


def test_constant_load_from_rest_with_given_markers(scene_path, tmp_path):
    path, scene = scene_path
    pts = tmp_path / "points.txt"
    np.savetxt(pts, [[0.2, 0.0, 0.0], [0.1, 0.02, 0.0]])
    out = tmp_path / "rec.npz"
    assert cli.main(["simulate", str(path), "--load", "0", "-0.2", "0", "--duration", "0.02",
                     "--markers", str(pts), "--out", str(out), "--quiet"]) == 0
    rec = load_recording(out)
    assert rec.at_rest_initially and rec.num_frames == 21 and rec.num_markers == 2
    np.testing.assert_allclose(rec.markers[0], np.loadtxt(pts))
    assert rec.markers[-1, 0, 1] < -1e-4  # gravity and the load pull the tip down


def test_default_markers_come_from_the_scene_recording(scene_path, tmp_path):
    path, scene = scene_path
    rest = np.array([[0.2, 0.02, 0.02], [0.15, -0.02, 0.0], [0.05, 0.0, 0.02]])
    save_recording(Recording([0.0, 0.01], rest, np.stack([rest, rest])), tmp_path / "train_0.npz")
    scene.recordings = [(tmp_path / "train_0.npz", "train")]
    save_scene(scene, path)
    out = tmp_path / "sim.npz"
    assert cli.main(["simulate", str(path), "--out", str(out), "--quiet"]) == 0
    rec = load_recording(out)
    np.testing.assert_allclose(rec.marker_rest, rest)
    np.testing.assert_allclose(rec.times[-1], 0.01)  # duration defaults to the recording's span
    # --replay 0 replays that recording (from its estimated held pose) at its times; an existing
    # --out is replaced only when asked (--force), never silently
    assert cli.main(["simulate", str(path), "--replay", "0", "--out", str(out), "--quiet"]) == 2
    np.testing.assert_allclose(load_recording(out).times[-1], 0.01)
    assert cli.main(["simulate", str(path), "--replay", "0", "--out", str(out), "--quiet", "--force"]) == 0
    np.testing.assert_allclose(load_recording(out).times, [0.0, 0.01])


def test_an_existing_recording_is_never_overwritten_silently(scene_path, tmp_path, capsys):
    path, scene = scene_path
    rest = np.array([[0.2, 0.02, 0.02], [0.15, -0.02, 0.0]])
    mine = tmp_path / "train_0.npz"
    save_recording(Recording([0.0, 0.01], rest, np.stack([rest, rest])), mine)
    scene.recordings = [(mine, "train")]
    save_scene(scene, path)
    before = mine.read_bytes()
    assert cli.main(["simulate", str(path), "--duration", "0.02", "--out", str(mine), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "one of the scene's recordings" in err and "--force" in err
    assert mine.read_bytes() == before


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--release"], "--release needs --load"),
        (["--load", "0", "1", "0", "--load-box", "5", "5", "5", "6", "6", "6"], "no free vertex"),
        (["--duration", "-1"], "--duration must be > 0"),
        (["--markers", "nope.txt"], "not found"),
        (["--replay", "3"], "--replay 3"),
        (["--model", "no_such_run"], "model run directory not found"),
        (["--load-box", *TIP_BOX], "give --load FX FY FZ too"),
        (["--frame-rate", "0"], "--frame-rate must be > 0"),  # 0 was read as "every step"
        (["--frame-rate", "-10"], "--frame-rate must be > 0"),
    ],
)
def test_errors_are_reported(scene_path, tmp_path, capsys, extra, message):
    path, _ = scene_path
    rc = cli.main(["simulate", str(path), "--out", str(tmp_path / "x.npz"), "--quiet", *extra])
    assert rc == 2
    assert message in capsys.readouterr().err


def test_missing_scene(tmp_path, capsys):
    assert cli.main(["simulate", str(tmp_path / "none.toml"), "--out", str(tmp_path / "x.npz")]) == 2
    assert "scene file not found" in capsys.readouterr().err


def test_model_and_vtu_mistakes_are_reported(scene_path, tmp_path, capsys):
    """--model given the model file instead of its run folder, a run folder whose model.npz is
    damaged (a killed copy), and a --vtu folder that already holds a series: each a clear error,
    no traceback, nothing overwritten."""
    path, _ = scene_path
    run = tmp_path / "run"
    run.mkdir()
    (run / "model.npz").write_bytes(b"")
    (run / "model.json").write_text('{"use": "rbf"}')
    out = str(tmp_path / "x.npz")
    assert cli.main(["simulate", str(path), "--out", out, "--quiet", "--model", str(run / "model.npz")]) == 2
    assert "is a file; pass the run folder" in capsys.readouterr().err
    assert cli.main(["simulate", str(path), "--out", out, "--quiet", "--model", str(run)]) == 2
    assert "the learned model cannot be read" in capsys.readouterr().err
    (run / "model.json").write_text('{"use": "nn"}')
    assert cli.main(["simulate", str(path), "--out", out, "--quiet", "--model", str(run)]) == 2
    assert "'use' must be 'rbf' or 'mlp', got 'nn'" in capsys.readouterr().err
    vtu = tmp_path / "vtu"
    args = ["simulate", str(path), "--quiet", "--duration", "0.01", "--all-surface", "--vtu", str(vtu)]
    assert cli.main([*args, "--out", out]) == 0
    first = sorted(p.name for p in vtu.iterdir())
    assert cli.main([*args, "--out", str(tmp_path / "y.npz")]) == 2
    assert "already holds a time series" in capsys.readouterr().err
    assert cli.main([*args[:4], "0.005", *args[5:], "--out", str(tmp_path / "y.npz"), "--force"]) == 0
    second = sorted(p.name for p in vtu.iterdir())
    assert len(second) < len(first) and set(second) <= set(first)  # no frame of the older series left


def test_version_and_out_paths_that_are_files(scene_path, tmp_path, capsys):
    path, _ = scene_path
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("matlearn ")
    f = tmp_path / "afile"
    f.write_text("x")
    for cmd in ("learn", "diagnose", "track"):
        assert cli.main([cmd, str(path), "--out", str(f)]) == 2
        assert f"--out {f} is a file" in capsys.readouterr().err, cmd
    assert cli.main(["track", str(path), "--out", str(tmp_path / "t")]) == 2
    assert "no recording is point clouds only" in capsys.readouterr().err
    assert cli.main(["track", str(path), "--out", str(path.parent), "--force"]) == 2  # never the input
    assert "is the scene's own folder" in capsys.readouterr().err


def test_input_slips_are_named_before_anything_is_written(scene_path, tmp_path, capsys):
    """A comma-separated --markers file, a --vtu that is a file (the recording was written before
    the error), a load with every vertex clamped, a duration that is no whole number of steps."""
    path, _ = scene_path
    out = tmp_path / "x.npz"
    csv = tmp_path / "points.csv"
    csv.write_text("0.1,0.02,0.0\n0.2,0.0,0.0\n")
    assert cli.main(["simulate", str(path), "--out", str(out), "--quiet", "--markers", str(csv)]) == 2
    assert "--markers " + str(csv) + ": expected x y z rest positions (m) separated by spaces" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("")
    assert cli.main(["simulate", str(path), "--out", str(out), "--quiet", "--duration", "0.01",
                     "--all-surface", "--vtu", str(afile)]) == 2
    assert "--vtu " + str(afile) + " is a file" in capsys.readouterr().err
    assert not out.exists()
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(5, 1, 1))
    held = Scene(mesh, Material(youngs_modulus=2e5), Damping(), np.arange(mesh.num_vertices), 1e-3)
    held_path = save_scene(held, tmp_path / "held" / "scene.toml")
    assert cli.main(["simulate", str(held_path), "--out", str(out), "--quiet", "--load", "0", "1", "0"]) == 2
    assert "every vertex is clamped" in capsys.readouterr().err
    assert cli.main(["simulate", str(path), "--out", str(out), "--quiet", "--duration", "0.0026",
                     "--all-surface"]) == 0
    assert "--duration 0.0026 s is not a whole number of time steps (0.001 s): 0.003 s simulated" in capsys.readouterr().err
    assert load_recording(out).times[-1] == pytest.approx(0.003)


def test_a_replayed_recording_without_a_first_pose_is_named(tmp_path, capsys):
    mesh = meshes.bar(0.2, 0.04, 0.04, cells=(5, 1, 1))
    rest = np.asarray(mesh.vertices)[meshes.surface_vertices(mesh)][:6]
    markers = np.repeat(rest[None], 4, axis=0)
    markers[0] = np.nan  # frame 0 unseen and not at rest: no first pose
    save_recording(Recording(0.001 * np.arange(4), rest, markers), tmp_path / "late.npz")
    scene = Scene(mesh, Material(youngs_modulus=2e5), Damping(), vertices_in_box(mesh.vertices, CLAMP), 1e-3,
                  recordings=[(tmp_path / "late.npz", "train")], fixed_box=CLAMP)
    path = save_scene(scene, tmp_path / "scene.toml")
    assert cli.main(["simulate", str(path), "--replay", "0", "--out", str(tmp_path / "x.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "recording 0 (late.npz): initial_state: no marker is seen in frame 0" in err and "at_rest_initially" in err


def test_every_subcommand_help_states_its_defaults(capsys):
    """--help shows each option's default where the help text does not already state it (a
    zero default included), and none for flags, required options or options without one."""
    def help_of(name):
        with pytest.raises(SystemExit):
            cli.main([name, "--help"])
        return " ".join(capsys.readouterr().out.split())

    assert "same seed gives the same model (default: 0)" in help_of("learn")
    ingest = help_of("ingest")
    assert "--poisson-ratio POISSON_RATIO dimensionless (default: 0.4)" in ingest
    assert "--time-step TIME_STEP s (default: 0.001)" in ingest
    # a flag: no default shown
    assert "--at-rest recordings start at rest (not held deformed) --time-step" in ingest
    assert "(default: None)" not in ingest and "(default: False)" not in ingest
    track = help_of("track")
    assert "--em-iterations EM_ITERATIONS corrections per frame (default: 2)" in track
    assert help_of("diagnose").count("default") >= 2
