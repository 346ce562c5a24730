"""A killed diagnosis resumes (`diagnose(..., resume=True)`, `matlearn diagnose --resume`): the
simulations it finished come from OUT/.diagnose_cache, the result is the uninterrupted one's, and
`matlearn diagnose` never overwrites an earlier or interrupted diagnosis silently."""
import json

import numpy as np
import pytest

from matlearn.cli import main
from matlearn.diagnosis import diagnose, simcache
from matlearn.recording import load_recording
from matlearn.scene import load_scene

from diagnosis_cases import FAST, tiny_case


class Killed(Exception):
    pass


def _numbers(x, path=""):
    """{json path: number} of every number in a diagnosis result."""
    out = {}
    if isinstance(x, dict):
        for k, v in x.items():
            out.update(_numbers(v, f"{path}/{k}"))
    elif isinstance(x, list):
        for i, v in enumerate(x):
            out.update(_numbers(v, f"{path}/{i}"))
    elif isinstance(x, (int, float)) and not isinstance(x, bool):
        out[path] = float(x)
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("resume")
    scene = tiny_case(tmp, "stiff", E_scale=1.5)
    whole = diagnose(scene, tmp / "whole", progress=lambda m: None, **FAST)
    lines = []

    def kill_after_sensitivities(msg):
        lines.append(msg)
        if "sensitivities done" in msg:
            raise Killed

    with pytest.raises(Killed):
        diagnose(scene, tmp / "killed", progress=kill_after_sensitivities, **FAST)
    stored = sorted((tmp / "killed" / simcache.FOLDER).glob("*.npz"))
    said = []
    resumed = diagnose(scene, tmp / "killed", progress=said.append, resume=True, **FAST)
    return dict(tmp=tmp, scene=scene, whole=whole, stored=len(stored), resumed=resumed, said=said)


def test_a_resumed_diagnosis_gives_the_uninterrupted_result(runs):
    whole, resumed = runs["whole"], runs["resumed"]
    assert runs["stored"] > 20  # the killed run had kept its simulations
    assert resumed["verdict"] == whole["verdict"] == ["stiffness_scale"]
    assert [e["name"] for e in resumed["effects"]] == [e["name"] for e in whole["effects"]]
    a, b = _numbers(whole), _numbers(resumed)
    assert a.keys() == b.keys()
    for k in a:  # the linearised replay's preconditioner history differs: round-off only
        assert b[k] == pytest.approx(a[k], rel=1e-6, abs=1e-12), k
    assert resumed["simulations"] == whole["simulations"]
    # the resumed run took the killed run's simulations instead of running them again
    assert any("resuming:" in m for m in runs["said"])
    last = runs["said"][-1]
    hits = int(last.split(", ")[1].split(" of them")[0])
    assert hits >= runs["stored"] - 2
    # and the cache is gone once diagnosis.json is written
    assert not (runs["tmp"] / "killed" / simcache.FOLDER).exists()
    assert json.loads((runs["tmp"] / "killed" / "diagnosis.json").read_text())["verdict"] == whole["verdict"]


def test_the_store_key_follows_every_input_of_a_simulation(runs, tmp_path):
    scene = load_scene(runs["scene"])
    rec = load_recording(scene.recording_paths("train")[0])
    store = simcache.SimulationStore(tmp_path / "c", resume=True)
    k = store.key(scene, rec, 1, "auto", b"model")
    assert store.key(scene, rec, 1, "auto", b"model") == k
    assert store.key(scene, rec, 8, "auto", b"model") != k  # another solver
    assert store.key(scene, rec, 1, False, b"model") != k  # another start decision
    assert store.key(scene, rec, 1, "auto", b"other") != k  # another model
    moved = load_recording(scene.recording_paths("train")[0])
    moved.markers = moved.markers.copy()
    moved.markers[3, 0, 1] += 1e-9  # one marker moved by a nanometre
    assert store.key(scene, moved, 1, "auto", b"model") != k
    scene2 = load_scene(runs["scene"])
    scene2.time_step = scene.time_step / 2
    assert store.key(scene2, rec, 1, "auto", b"model") != k
    # what is put is what comes back, bit for bit (and only to a resumed run)
    X = np.random.default_rng(0).standard_normal((5, 4, 3))
    Y = np.arange(6.0).reshape(2, 3)
    store.put(k, X, Y)
    got = store.get(k)
    assert len(got) == 2
    np.testing.assert_array_equal(got[0], X)
    np.testing.assert_array_equal(got[1], Y)
    assert store.get(store.key(scene, rec, 8, "auto", b"model")) is None
    fresh = simcache.SimulationStore(tmp_path / "d")
    fresh.put(k, X)
    assert fresh.get(k) is None


def test_a_store_written_by_other_code_or_without_resume_is_not_used(tmp_path):
    folder = tmp_path / simcache.FOLDER
    store = simcache.SimulationStore(folder)
    store.put("a" * 40, np.zeros((1, 1, 3)))
    assert simcache.SimulationStore(folder, resume=True).resumed == 1
    (folder / "manifest.json").write_text(json.dumps({"format": 1, "code": "another matlearn"}))
    assert simcache.SimulationStore(folder, resume=True).resumed == 0  # discarded
    store = simcache.SimulationStore(folder)
    store.put("b" * 40, np.zeros((1, 1, 3)))
    assert simcache.SimulationStore(folder, resume=False).resumed == 0  # a fresh run starts afresh
    assert not list(folder.glob("*.npz"))


def test_cli_never_overwrites_a_diagnosis_silently(runs, tmp_path, capsys, monkeypatch):
    import matlearn.diagnosis as diag

    calls = []

    def fake(scene, out, **kw):
        calls.append(kw["resume"])
        return {"verdict": [], "gap_before": {"max_error_pct": 1.0}}

    monkeypatch.setattr(diag, "diagnose", fake)
    done = runs["tmp"] / "whole"  # holds diagnosis.json
    assert main(["diagnose", str(runs["scene"]), "--out", str(done), "--no-report"]) == 2
    assert "earlier diagnosis" in capsys.readouterr().err
    interrupted = tmp_path / "interrupted"
    (interrupted / simcache.FOLDER).mkdir(parents=True)
    assert main(["diagnose", str(runs["scene"]), "--out", str(interrupted), "--no-report"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert calls == []
    assert main(["diagnose", str(runs["scene"]), "--out", str(interrupted), "--no-report", "--resume"]) == 0
    assert main(["diagnose", str(runs["scene"]), "--out", str(done), "--no-report", "--force"]) == 0
    assert main(["diagnose", str(runs["scene"]), "--out", str(tmp_path / "new"), "--no-report"]) == 0
    assert calls == [True, False, False]


def test_cli_resumes_a_diagnosis_killed_by_sigkill(runs, tmp_path):
    """The real case: `matlearn diagnose` killed (SIGKILL, no cleanup) part way, then the same
    command with --resume: the verdict of the uninterrupted run, the finished simulations reused."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "matlearn", "diagnose", str(runs["scene"]), "--out", str(out), "--no-report"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    folder = out / simcache.FOLDER

    def finished():  # a simulation being written is a hidden ".KEY.PID.tmp.npz" until renamed
        return len([f for f in folder.glob("*.npz") if not f.name.startswith(".")])

    t0 = time.time()
    while time.time() - t0 < 120 and p.poll() is None and finished() < 60:
        time.sleep(0.05)
    assert p.poll() is None, "the diagnosis ended before it could be killed"
    p.send_signal(signal.SIGKILL)
    p.wait()
    p.stdout.close()
    p.stderr.close()
    assert not (out / "diagnosis.json").exists()
    kept = finished()
    assert kept >= 60
    # without --resume the command refuses the interrupted folder
    again = subprocess.run(cmd, capture_output=True, text=True)
    assert again.returncode == 2 and "--resume" in again.stderr
    done = subprocess.run(cmd + ["--resume"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"resuming: {kept} simulation(s)" in done.stderr
    result = json.loads((out / "diagnosis.json").read_text())
    assert result["verdict"] == runs["whole"]["verdict"]  # (the CLI's defaults, not FAST: same verdict)
    assert not folder.exists()
