"""Learning started from the baseline fit (learning/start.py: E, nu, alpha_K fitted, alpha_M held): iteration 0 is exactly the
baseline, the learned train error never ends above it, and the saved model carries the fitted
parameters so `matlearn simulate --model RUN` reproduces the learned model."""
import json

import numpy as np
import pytest

from matlearn import cli
from matlearn.learning import LearnOptions, learn, load_model
from matlearn.learning import start as start_mod
from matlearn.learning.io import scene_model
from matlearn.recording import load_recording
from matlearn.replay import score
from matlearn.scene import load_scene

from learning_cases import small_bar_case


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    return small_bar_case(tmp_path_factory.mktemp("cases"))


def test_learning_from_the_baseline_starts_at_it_and_never_ends_above_it(case, tmp_path, monkeypatch):
    sc = load_scene(case)
    lscene, info = start_mod.baseline_start(sc, tmp_path / "run", max_evaluations=8)
    E0, E1 = float(np.mean(sc.material.youngs_modulus)), info["material"]["youngs_modulus"]
    # truth: neo-Hookean E = 2e5, nu = 0.43, alpha_K = 0.004 (small strains: co-rotated-like);
    # nominal co-rotated E = 3.5e5. The 3-parameter fit recovers the truth's moduli.
    assert E0 == pytest.approx(3.5e5) and E1 == pytest.approx(2e5, rel=0.02)
    assert info["material"]["poisson_ratio"] == pytest.approx(0.43, abs=0.01)
    assert info["damping"]["alpha_stiffness"] == pytest.approx(0.004, rel=0.1)
    # alpha_M is held at the nominal value (the learner has no mass-damping term to undo it)
    assert lscene.damping.alpha_mass == sc.damping.alpha_mass
    base_train = score(sc, sc.model(material=lscene.material, damping=lscene.damping), "train", start="held")
    nominal_train = score(sc, sc.model(), "train")
    assert base_train["max_error_pct"] < nominal_train["max_error_pct"]
    res = learn(lscene, tmp_path / "run", LearnOptions(iterations=2, modes=12, centers=12), log=None)
    start_train = res["nominal"]["train"]["max_error_pct"]
    # Iteration 0 is the baseline model itself (same simulation as the baseline's scoring).
    assert start_train == pytest.approx(base_train["max_error_pct"], rel=1e-6)
    assert res["final"]["train"]["max_error_pct"] <= start_train
    print("train nominal", nominal_train["max_error_pct"], "baseline", start_train,
          "learned", res["final"]["train"]["max_error_pct"])
    # The fit is cached in RUN/start.json: a resumed run does not fit again.
    monkeypatch.setattr(start_mod, "fit_parameters", lambda *a, **k: pytest.fail("fitted again"))
    again, info2 = start_mod.baseline_start(sc, tmp_path / "run")
    assert info2["material"] == info["material"] and info2["damping"] == info["damping"]
    assert again.damping.alpha_stiffness == lscene.damping.alpha_stiffness


def _cli_learn(case, tmp_path, start, *extra):
    """One short `matlearn learn` run from the given start; returns its run folder."""
    out = tmp_path / "run"
    rc = cli.main(["learn", str(case), "--out", str(out), "--iterations", "1", "--modes", "10",
                   "--centers", "8", "--no-distill", "--quiet", "--start", start, *extra])
    assert rc == 0
    return out


def test_cli_baseline_start_saves_the_fitted_parameters_and_simulate_reproduces_it(case, tmp_path):
    # every standard law fitted: the kept one (the lowest train rms) is the law the saved model
    # rebuilds, whichever it is
    out = _cli_learn(case, tmp_path, "baseline", "--laws", "all")
    meta = json.loads((out / "model.json").read_text())
    assert meta["start"] == "baseline"
    by_law = json.loads((out / "start.json").read_text())["train_rms_pct_by_law"]
    assert set(by_law) == set(start_mod.STANDARD_LAWS)
    assert meta["base_material"]["model"] == min(by_law, key=by_law.get)
    sc = load_scene(case)
    assert meta["base_material"]["youngs_modulus"] != pytest.approx(float(np.mean(sc.material.youngs_modulus)))
    full = scene_model(sc, out)
    partial = sc.model(load_model(out))  # the correction on the scene's nominal parameters
    idx = [p for p, _ in sc.recordings].index(sc.recording_paths("test")[0])
    rec_out = tmp_path / "replay.npz"
    assert cli.main(["simulate", str(case), "--model", str(out), "--replay", str(idx),
                     "--out", str(rec_out), "--quiet"]) == 0
    sim = load_recording(rec_out)
    learned = score(sc, full, "test")["recordings"][0]["max_error_pct"]
    summary = json.loads((out / "summary.json").read_text())
    best = summary["final"]["test"]["max_error_pct"]
    assert learned == pytest.approx(best, rel=1e-6)
    # simulate --model used the fitted parameters: its markers are those of `full`, not `partial`
    # (simulate --replay starts from the held pose, replay.initial_state's default: compared with
    # `full` scored from that same start)
    test_rec = load_recording(sc.recording_paths("test")[0])
    err = np.linalg.norm(sim.markers - test_rec.markers, axis=2).max() / sc.object_size * 100
    held = score(sc, full, "test", start="held")["recordings"][0]["max_error_pct"]
    assert err == pytest.approx(held, rel=1e-3, abs=1e-4)
    wrong = score(sc, partial, "test")["recordings"][0]["max_error_pct"]
    assert abs(wrong - learned) > 0.1 * learned


def _start_name(scene):
    """Which start a scene is: 'field' (a per-element modulus), 'nominal' (E = 3.5e5) or 'baseline'."""
    E = np.asarray(scene.material.youngs_modulus, float)
    if E.ndim and np.ptp(E) > 0:
        return "field"
    return "nominal" if np.mean(E) == pytest.approx(3.5e5) else "baseline"


def _fake_learn(train, test, tracked=None):
    """A learn() stand-in: per start (told apart by the scene's E, _start_name) a fixed learned
    train and test max error; the scene it learned on is tracked(scene) (learn's cloud-only
    recordings replaced by tracked markers; default: the scene)."""
    calls = []

    def learn_fn(scene, run_dir, options, resume=False, log=None):
        name = _start_name(scene)
        calls.append((name, str(run_dir)))
        fin = {"train": {"max_error_pct": train[name]},
               "test": {"max_error_pct": max(test[name]), "per_recording_max_pct": test[name]}}
        return {"final": fin, "nominal": fin, "metrics": [], "best_iteration": 1, "params": None,
                "scene": tracked(scene) if tracked else scene}
    return learn_fn, calls


@pytest.mark.parametrize("train,chosen", [({"nominal": 0.13, "baseline": 0.20, "field": 0.15}, "nominal"),
                                          ({"nominal": 0.20, "baseline": 0.13, "field": 0.15}, "baseline"),
                                          ({"nominal": 0.20, "baseline": 0.15, "field": 0.13}, "field"),
                                          ({"nominal": 0.20, "baseline": 0.20, "field": 0.20}, "baseline"),
                                          ({"nominal": 0.13, "baseline": 0.20, "field": 0.13}, "nominal")])
def test_best_start_keeps_the_lower_train_error_and_never_looks_at_the_test(case, tmp_path, monkeypatch,
                                                                             train, chosen):
    from matlearn.learning import field as field_mod

    sc = load_scene(case)
    fitted = {"material": sc.material.__class__("corotated", 2e5, 0.43, 1000.0),
              "damping": sc.damping.__class__(0.0, 0.004), "evaluations": 1}
    fits = []
    monkeypatch.setattr(start_mod, "fit_parameters", lambda *a, **k: fits.append(1) or fitted)
    nt = sc.mesh.num_tets
    E_field = 2e5 * np.exp(0.1 * np.sin(np.arange(nt)))

    def fake_field(scene, material, damping, **kw):
        assert float(np.mean(material.youngs_modulus)) == pytest.approx(2e5)  # on the baseline fit
        return material.__class__(material.model, E_field, material.poisson_ratio, material.density), {}
    monkeypatch.setattr(field_mod, "fit_stiffness_field", fake_field)
    # the test errors always favour the starts the train errors reject (ties: the fewest parameters)
    test = {n: ([0.9, 0.9] if n == chosen else [0.1, 0.1]) for n in train}
    learn_fn, calls = _fake_learn(train, test)
    scene, info, res, run = start_mod.learn_best_start(sc, tmp_path / "run", learn_fn=learn_fn)
    assert sorted(c[0] for c in calls) == ["baseline", "field", "nominal"]
    assert {c[1] for c in calls} == {str(tmp_path / "run" / f"start_{n}") for n in ("nominal", "baseline", "field")}
    assert len(fits) == 1  # the field builds on the baseline start's fit, not a second one
    assert info["start"] == "best" and info["chosen"] == chosen
    assert res["final"]["train"]["max_error_pct"] == train[chosen]
    assert run == tmp_path / "run" / f"start_{chosen}" == start_mod.chosen_run(tmp_path / "run")
    # the kept scene and the saved base parameters are those of the kept start
    E = np.asarray(scene.material.youngs_modulus, float)
    want = {"baseline": 2e5, "nominal": 3.5e5, "field": E_field}[chosen]
    np.testing.assert_allclose(np.broadcast_to(E, (nt,)), np.broadcast_to(want, (nt,)))
    assert ("material" in info) == (chosen != "nominal")
    assert ("material_homogeneous" in info) == (chosen == "field")
    assert info["test_per_recording_max_pct"][chosen] == [0.9, 0.9]  # recorded, not used
    # every start's model is saved in its folder; a kept field names the best homogeneous start's
    for n in start_mod.STARTS:
        assert json.loads((tmp_path / "run" / f"start_{n}" / "model.json").read_text())["start"] == n
    alt = start_mod.transfer_start(train)
    assert info.get("transfer_start") == (alt if chosen == "field" else None)
    assert start_mod.model_meta(info).get("transfer_model") == (f"start_{alt}" if chosen == "field" else None)
    assert start_mod.chosen_run(tmp_path / "elsewhere") == tmp_path / "elsewhere"


def test_cli_best_start_keeps_the_lower_train_run_and_its_model_replays(case, tmp_path):
    out = _cli_learn(case, tmp_path, "best")
    best = json.loads((out / "best_start.json").read_text())
    train = best["train_max_error_pct"]
    assert best["chosen"] == min(train, key=train.get)
    assert start_mod.chosen_run(out) == out / f"start_{best['chosen']}"
    for name in start_mod.STARTS:  # each start ran in its own folder
        metrics = json.loads((out / f"start_{name}" / "metrics.json").read_text())
        assert min(m["train"]["max_error_pct"] for m in metrics["iterations"]) == pytest.approx(train[name])
    meta = json.loads((out / "model.json").read_text())
    assert meta["start"] == "best" and ("base_material" in meta) == (best["chosen"] != "nominal")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["start"]["chosen"] == best["chosen"]
    # "nominal" in the summary is the kept start's iteration 0, and says so
    assert summary["nominal_model"] == ("nominal" if best["chosen"] == "nominal" else f"{best['chosen']} start")
    sc = load_scene(case)
    learned = score(sc, scene_model(sc, out), "test")["recordings"][0]["max_error_pct"]
    assert learned == pytest.approx(summary["final"]["test"]["max_error_pct"], rel=1e-6)


def test_baseline_start_keeps_the_law_with_the_lower_train_rms(case, monkeypatch):
    """With several laws the start is the fit with the lowest train rms (its law becomes the
    nominal law the correction is learned on), each fit warm-started from its own law's fit."""
    from matlearn.materials import Damping, Material

    sc = load_scene(case)
    rms = {"corotated": 0.5, "neo_hookean": 0.1}
    warmed = {}

    def fake_fit(scene, law, max_evaluations=20, alpha_mass=None, start=None):
        warmed[law] = start
        return {"material": Material(law, 2e5 if law == "neo_hookean" else 3e5, 0.4, 1000.0),
                "damping": Damping(alpha_mass, 0.004), "evaluations": 3, "train_rms_pct": rms[law]}

    monkeypatch.setattr(start_mod, "fit_parameters", fake_fit)
    warm = {law: {"material": Material(law, 1e5, 0.4, 1000.0)} for law in rms}
    lscene, info = start_mod.baseline_start(sc, None, warm=warm, laws=tuple(rms))
    assert lscene.material.model == "neo_hookean" and info["material"]["youngs_modulus"] == 2e5
    assert info["train_rms_pct_by_law"] == rms
    assert all(warmed[law] is warm[law] for law in rms)
    rms["corotated"] = 0.05
    assert start_mod.baseline_start(sc, None, warm=warm, laws=tuple(rms))[0].material.model == "corotated"
    # default: the scene's own law only; a single warm fit is used for its own law only
    lscene, info = start_mod.baseline_start(sc, None, warm=warm["neo_hookean"])
    assert lscene.material.model == sc.material.model == "corotated" and warmed["corotated"] is None


def test_the_start_finds_the_standard_law_of_the_recordings(tmp_path):
    """A St. Venant-Kirchhoff bar bent far (tip strains of several %) from a co-rotated nominal:
    with every standard law the start fits, the StVK fit explains the train recording best and
    is kept, with the truth's moduli; the co-rotated fit alone leaves a larger rms."""
    from matlearn import meshes
    from matlearn.materials import Damping, Material
    from matlearn.synthetic import Motion, make_case

    L = 0.08
    mesh = meshes.bar(L, 0.01, 0.01, cells=(8, 1, 1))
    tip = [[L - 0.011, -1, -1], [1, 1, 1]]
    path = make_case(tmp_path, "stvk_bar", mesh, Material("stvk", 2e5, 0.4, 1000.0), Damping(0.0, 0.004),
                     mesh, Material("corotated", 3e5, 0.4, 1000.0), Damping(0.0, 0.004),
                     [[-1, -1, -1], [1e-4, 1, 1]],
                     [Motion("release", "train", 0.08, load={"box": tip, "force": [0.6, 0.25, 0.0]})],
                     marker_fraction=0.5, seed=2)
    sc = load_scene(path)
    lscene, info = start_mod.baseline_start(sc, None, max_evaluations=12, laws=start_mod.STANDARD_LAWS)
    rms = info["train_rms_pct_by_law"]
    assert set(rms) == set(start_mod.STANDARD_LAWS)
    assert lscene.material.model == "stvk" and min(rms, key=rms.get) == "stvk"
    assert info["material"]["youngs_modulus"] == pytest.approx(2e5, rel=0.03)
    assert rms["stvk"] < 0.3 * rms["corotated"]


def test_learn_laws_option():
    from matlearn.commands.learn import _laws

    assert _laws("own") is None and _laws("all") == start_mod.STANDARD_LAWS
    assert _laws("stvk, corotated") == ("stvk", "corotated")
    with pytest.raises(ValueError, match="unknown law"):
        _laws("mooney")


def test_a_kept_fields_transfer_model_prefers_the_fitted_law_on_a_near_tie():
    """Another mesh gets the best homogeneous start's model; within TRANSFER_TIE of the lowest
    learned train error the fitted law wins (the StVK bar: 0.1590 nominal vs 0.1596 % fitted)."""
    t = start_mod.transfer_start
    assert t({"nominal": 0.1590, "baseline": 0.1596, "field": 0.077}) == "baseline"
    assert t({"nominal": 0.100, "baseline": 0.120, "field": 0.05}) == "nominal"  # 20 % apart
    assert t({"nominal": 0.20, "baseline": 0.10, "field": 0.05}) == "baseline"
    tie = 1 + start_mod.TRANSFER_TIE
    assert t({"nominal": 0.1, "baseline": 0.1 * tie * 0.999, "field": 0.0}) == "baseline"
    assert t({"nominal": 0.1, "baseline": 0.1 * tie * 1.001, "field": 0.0}) == "nominal"


def test_a_kept_fitted_start_with_a_free_stress_scale_gives_other_meshes_the_nominal_starts_model(
        tmp_path, monkeypatch):
    """A slowly driven bar does not fix the stress scale (identify.py): where the fitted start is
    kept, another mesh gets the nominal start's model, the user's modulus, not the fitted one."""
    import dataclasses

    from matlearn import meshes
    from matlearn.learning import field as field_mod
    from matlearn.learning.io import save_model

    from learning_cases import driven_bar

    driven = load_scene(driven_bar(tmp_path / "cases"))
    # the recordings as a cloud-only scene has them before learn tracks them: none with markers;
    # the check must run on the scene learned on (the tracked one), with the start's material
    sc = dataclasses.replace(driven, recordings=[])
    fitted = {"material": sc.material.__class__("corotated", 1.2e5, 0.43, 1000.0),
              "damping": sc.damping.__class__(0.0, 0.004), "evaluations": 1}
    monkeypatch.setattr(start_mod, "fit_parameters", lambda *a, **k: fitted)
    monkeypatch.setattr(field_mod, "fit_stiffness_field", lambda scene, material, damping, **kw: (
        material.__class__(material.model, material.youngs_modulus * np.linspace(0.9, 1.1, scene.mesh.num_tets),
                           material.poisson_ratio, material.density), {}))
    train = {"nominal": 0.20, "baseline": 0.10, "field": 0.15}
    learn_fn, _ = _fake_learn(train, {n: [0.1] for n in train},
                              tracked=lambda s: dataclasses.replace(s, recordings=driven.recordings))
    scene, info, res, run = start_mod.learn_best_start(sc, tmp_path / "run", learn_fn=learn_fn)
    assert info["chosen"] == "baseline" and not info["stress_scale"]["determined"]
    assert info["transfer_start"] == "nominal"
    save_model(tmp_path / "run", start_mod.zero_params(), None, meta={"start": "best", **start_mod.model_meta(info)})
    E = lambda m: float(np.mean(2 * m.mu * (1 + 0.43)))  # noqa: E731
    assert E(scene_model(sc, tmp_path / "run")) == pytest.approx(1.2e5)  # its own mesh: the kept fit
    other = dataclasses.replace(sc, mesh=meshes.bar(0.06, 0.02, 0.02, cells=(4, 1, 1)), fixed=[], recordings=[])
    assert E(scene_model(other, tmp_path / "run")) == pytest.approx(3.5e5)  # another: the nominal
    # the same choice on a release, whose recordings fix the scale: no transfer model
    rel = load_scene(small_bar_case(tmp_path / "rel"))
    _, info, _, _ = start_mod.learn_best_start(rel, tmp_path / "run_rel", learn_fn=_fake_learn(train, {
        n: [0.1] for n in train})[0])
    assert info["chosen"] == "baseline" and info["stress_scale"]["determined"]
    assert "transfer_start" not in info and "transfer_model" not in start_mod.model_meta(info)
