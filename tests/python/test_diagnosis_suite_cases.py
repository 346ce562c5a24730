"""The diagnosis benchmark's case builder (bench/diagnosis_suite_cases.py, bench/diagnosis_suite.py):
truths really carry their effect, motions are lab-like, the random set is a function of its seed."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path.insert(0, str(BENCH))

import diagnosis_suite_cases as dc  # noqa: E402
import diagnosis_suite as ds  # noqa: E402
from matlearn import replay  # noqa: E402
from matlearn.scene import load_scene  # noqa: E402

SMALL = {"kind": "bar", "L": 0.12, "W": 0.03, "H": 0.03, "cells": (4, 2, 2)}


def _spec(truth, motions=(("load", "train", 0.04, 1.57), ("load", "test", 0.06, 4.71)), effects=()):
    return {"effects": list(effects), "shape": SMALL, "truth": truth, "motions": list(motions),
            "E0": 1.5e6, "nu0": 0.4, "rho0": 1000.0, "duration": 0.08}


def _nominal_gap(path):
    scene = load_scene(path)
    return replay.score(scene, role="test")["max_error_pct"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    work = tmp_path_factory.mktemp("suite")
    ctrl, _ = ds.build_case(work, "ctrl", _spec({}), seed=3, reuse=False)
    stiff, _ = ds.build_case(work, "stiff", _spec({"stiffness_scale": 0.5}, effects=["stiffness_scale"]),
                             seed=3, reuse=False)
    return work, ctrl, stiff


def test_strong_effect_gap_exceeds_control(built):
    # a softer truth adds to the coarse model's discretisation stiffness; the gap must grow clearly
    _, ctrl, stiff = built
    g_ctrl, g_stiff = _nominal_gap(ctrl), _nominal_gap(stiff)
    assert g_stiff > 2.0 * g_ctrl, (g_ctrl, g_stiff)
    # the effect alone (truth vs its effect-free twin on the same fine mesh) is most of the gap
    work = Path(stiff).parent.parent
    spec = _spec({"stiffness_scale": 0.5}, effects=["stiffness_scale"])
    size = ds.effect_size(work, "stiff", spec, seed=3)
    assert 0.5 * g_stiff < size < 1.5 * g_stiff, (size, g_stiff)
    assert ds.effect_size(work, "ctrl", _spec({}), seed=3) is None


def test_case_is_a_release_with_finer_truth_and_sparse_markers(built):
    work, ctrl, _ = built
    truth = json.loads((work / "ctrl" / "truth.json").read_text())
    assert truth["truth_mesh"]["tets"] > 2 * truth["model_mesh"]["tets"]
    assert 0.1 < truth["marker_fraction"] < 0.5 and truth["noise"] > 0
    scene = load_scene(ctrl)
    train, test = scene.recordings_with_role("train")[0], scene.recordings_with_role("test")[0]
    assert not train.at_rest_initially  # held, then released
    amp = lambda r: np.nanmax(np.linalg.norm(r.markers[0] - r.marker_rest, axis=1))  # noqa: E731
    # the load is set from the nominal compliance: ~4 % and ~6 % of the length at the tip
    assert 0.025 * 0.12 < amp(train) < 0.06 * 0.12
    assert amp(test) > 1.2 * amp(train)


def test_flick_starts_deformed_near_a_turning_point(tmp_path):
    spec = _spec({}, motions=[("flick", "train", 0.04, 0.0), ("drop", "test", 0, 0)])
    path, _ = ds.build_case(tmp_path, "flick", spec, seed=1, reuse=False)
    scene = load_scene(path)
    rec = scene.recordings_with_role("train")[0]
    d = np.linalg.norm(rec.markers - rec.marker_rest, axis=2).max(axis=1)
    assert d[0] > 0.01 * 0.12  # swung out
    v = np.linalg.norm(np.diff(rec.markers, axis=0), axis=2).max(axis=1) / np.diff(rec.times)
    assert v[0] < 0.5 * v.max()  # starts near rest, then moves
    drop = scene.recordings_with_role("test")[0]
    assert drop.at_rest_initially


def test_random_set_is_deterministic_and_valid():
    a, b, c = dc.random_specs(7, 12), dc.random_specs(7, 12), dc.random_specs(8, 12)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert json.dumps(a, sort_keys=True) != json.dumps(c, sort_keys=True)
    for spec in list(a.values()) + list(c.values()):
        assert set(spec["effects"]) <= set(dc.EFFECTS) and len(spec["effects"]) <= 2
        assert set(spec["truth"]) == set(spec["effects"])
        roles = [m[1] for m in spec["motions"]]
        assert roles.count("train") == 2 and roles.count("test") == 1
        test_amp = [m[2] for m in spec["motions"] if m[1] == "test"][0]
        assert test_amp > max(m[2] for m in spec["motions"] if m[1] == "train")


def test_named_set_covers_the_vocabulary():
    specs = dc.named_specs()
    assert len(specs) == 14
    covered = set().union(*(s["effects"] for s in specs.values()))
    assert covered == set(dc.EFFECTS)
    assert {s["shape"]["kind"] for s in specs.values()} >= {"bar", "plate", "capsule", "sphere"}


def test_heterogeneity_region_maps_to_model_elements():
    spec = _spec({"heterogeneity": (0.25, 0.6, 2.5)}, effects=["heterogeneity"])
    model, truth, clamp, tip, axis, L = dc.make_shape(SMALL)
    mat, _, _, region = dc.build_truth(spec, truth, model, axis, clamp)
    E = np.asarray(mat.youngs_modulus)
    assert np.isclose(E.max() / E.min(), 2.5)
    C = np.asarray(model.vertices)[np.asarray(model.tets)].mean(axis=1)
    assert np.all((C[region, 0] >= 0.25 * L) & (C[region, 0] <= 0.6 * L)) and len(region) > 0


def test_a_case_whose_truth_cannot_be_built_is_reported_not_scored_and_the_run_goes_on(tmp_path, monkeypatch):
    """A random spec can ask for a truth the simulator cannot hold (e.g. a strongly softening
    compression law): the row says so, the totals leave it out, the next case still runs
    (random seed 3's last case used to stop the run without a results file)."""
    specs = {"a_control": {"effects": []}, "b_bad": {"effects": ["compression_nonlinearity"]}}
    calls = []

    def build(work, name, spec, seed, reuse=True):
        calls.append(name)
        if name == "b_bad":
            raise RuntimeError("static_solve: Newton did not converge")
        return tmp_path / name / "scene.toml", None

    def diagnose(*a, **k):  # a built case whose diagnosis fails still counts
        raise ValueError("diagnosis failed")

    monkeypatch.setattr(ds, "build_case", build)
    monkeypatch.setattr(ds, "diagnose", diagnose)
    monkeypatch.setattr(ds, "effect_size", lambda work, name, *a: None if name == "a_control"
                        else pytest.fail("no effect size without a case"))
    rows = ds.run_set({k: dict(v, shape={"kind": "bar"}, motions=[]) for k, v in specs.items()},
                      tmp_path, ["b_bad", "a_control"], fresh=True, rediagnose=False)
    assert calls == ["b_bad", "a_control"]
    bad = next(r for r in rows if r["case"] == "b_bad")
    assert bad["truth_failed"] and bad["error"].startswith("truth could not be built")
    t = ds.totals(rows)
    assert t["truth_failed_cases"] == ["b_bad"] and t["cases"] == 1
    assert t["top1_accuracy"] is None and t["failed_cases"] == ["a_control"]
    assert t["control_clean"] is False
