"""diagnosis.json follows formats.md whatever the fits gave: every effect's gap_after is an
object with two finite numbers, and the file is strict JSON (no NaN / Infinity tokens)."""
import json

import numpy as np
import pytest

from matlearn.diagnosis import contract


def _result():
    return {
        "object_size": np.float64(0.1),
        "gap_before": {"max_error_pct": 2.0, "rms_error_pct": np.float32(0.5)},
        "where": {"regions": [{"elements": np.array([3, 4]), "share": 0.5, "centroid": np.zeros(3)}],
                  "frames": {"share_by_time": [[0.0, 1.0]]},
                  "regime": {"tension": 0.5, "compression": 0.5, "elastic": 1.0, "dissipative": 0.0}},
        "effects": [
            {"name": "stiffness_scale", "explained": 0.9, "score": -10.0, "parameters": {"scale": 1.2},
             "gap_after": {"max_error_pct": 1.0, "rms_error_pct": 0.2}},
            # a fitted model the held-out motion could not be simulated with
            {"name": "tension_nonlinearity", "explained": 0.1, "score": -5.0,
             "parameters": {"c2": 0.1, "c3": float("nan")}, "gap_after": None},
            {"name": "poisson_ratio", "explained": 0.0, "score": float("-inf"), "parameters": {}},
        ],
        "verdict": ["stiffness_scale"],
    }


def _strict(text):
    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")
    return json.loads(text, parse_constant=refuse)


def test_plain_json_dump_of_such_a_result_is_not_strict_json():
    # the failure mode the contract removes (guards the test itself)
    with pytest.raises(ValueError):
        _strict(json.dumps(_result(), default=lambda o: o.tolist()))


def test_conformed_result_is_strict_json_with_every_gap_an_object(tmp_path):
    res = contract.write(_result(), tmp_path / "diagnosis.json")
    d = _strict((tmp_path / "diagnosis.json").read_text())
    assert d == json.loads(json.dumps(res))
    for e in d["effects"]:
        g = e["gap_after"]
        assert set(g) == {"max_error_pct", "rms_error_pct"}
        assert all(isinstance(v, float) and np.isfinite(v) for v in g.values())
    rows = {e["name"]: e for e in d["effects"]}
    # a gap that could not be computed is one object size and says so; a computed one is kept
    assert rows["tension_nonlinearity"]["gap_after"]["max_error_pct"] == contract.FAILED_GAP_PCT
    assert rows["tension_nonlinearity"]["held_out_failed"] is True
    assert rows["poisson_ratio"]["held_out_failed"] is True
    assert rows["stiffness_scale"]["gap_after"] == {"max_error_pct": 1.0, "rms_error_pct": 0.2}
    assert "held_out_failed" not in rows["stiffness_scale"]
    # non-finite numbers become null and are listed, numpy values become plain JSON
    assert rows["tension_nonlinearity"]["parameters"]["c3"] is None
    assert rows["poisson_ratio"]["score"] is None
    assert sorted(d["nonfinite"]) == ["effects[1].parameters.c3", "effects[2].score"]
    assert d["where"]["regions"][0]["elements"] == [3, 4]
    assert d["gap_before"]["rms_error_pct"] == 0.5


def test_a_clean_result_is_unchanged():
    r = _result()
    r["effects"] = r["effects"][:1]
    before = json.loads(json.dumps(r, default=lambda o: o.tolist()))
    assert contract.conform(r) == before


def test_mesh_advice_follows_what_the_mesh_alone_does():
    """An empty verdict whose gap the once-refined mesh halves: refine the mesh; one that only the
    stiffness factor halves while the refined mesh does not (independent seed 14's stiffer,
    damped torus: 4.54 % before, 1.34 % with the factor, 7.20 % refined): a stiffness change the
    mesh's error hides, not advice to refine; an effect found, or a mesh that explains little:
    nothing."""
    from matlearn.diagnosis.report import mesh_advice

    def result(verdict, factor, refined, before=4.54):
        gap = lambda x: None if x is None else {"max_error_pct": x, "rms_error_pct": x / 3}  # noqa: E731
        return {"verdict": verdict, "gap_before": gap(before),
                "discretisation": {"stiffness_factor": 0.778, "gap_with_offset": gap(factor),
                                   "gap_refined_mesh": gap(refined)}}

    assert "refine the mesh" in mesh_advice(result([], 4.0, 1.2))
    hidden = mesh_advice(result([], 1.34, 7.20))
    assert "E x 0.778" in hidden and "refine the mesh" not in hidden
    assert "refine the mesh (or scale E by 0.778" in mesh_advice(result([], 1.34, None))
    assert mesh_advice(result(["stiffness_scale"], 1.34, 1.2)) is None
    assert mesh_advice(result([], 3.0, 3.5)) is None
