"""End to end: a withheld stiffness scale is attributed to stiffness_scale, the held-out gap
shrinks, and diagnosis.json follows formats.md (vocabulary, shares, ranking)."""
import json

import numpy as np
import pytest

from matlearn.cli import main
from matlearn.diagnosis import VOCABULARY, diagnose

from diagnosis_cases import FAST, tiny_case


@pytest.fixture(scope="module")
def stiff(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("diag")
    scene = tiny_case(tmp, "stiff", E_scale=1.5)
    result = diagnose(scene, tmp / "out", progress=lambda m: None, **dict(FAST, report=True))
    return result, tmp / "out"


def test_stiffness_scale_is_attributed_and_the_gap_shrinks(stiff):
    result, _ = stiff
    assert result["verdict"][:1] == ["stiffness_scale"]
    e = next(e for e in result["effects"] if e["name"] == "stiffness_scale")
    # truth 1.5 x E on a finer mesh; the coarse model's own stiffening is compensated
    assert 1.25 < e["parameters"]["scale"] < 1.9
    # what remains is mostly the coarse mesh's own shape error
    assert e["gap_after"]["max_error_pct"] < 0.75 * result["gap_before"]["max_error_pct"]
    assert e["gap_after"]["rms_error_pct"] < 0.75 * result["gap_before"]["rms_error_pct"]
    # density cannot be told apart (all loads are accelerations): flagged, not guessed
    assert "density" in e.get("confounded_with", [])


def test_diagnosis_json_follows_the_public_format(stiff):
    _, out = stiff
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["object_size"] > 0
    for key in ("max_error_pct", "rms_error_pct"):
        assert d["gap_before"][key] >= 0
    regions = d["where"]["regions"]
    assert regions and sum(r["share"] for r in regions) <= 1 + 1e-9
    for r in regions:
        assert len(r["centroid"]) == 3 and all(isinstance(e, int) for e in r["elements"])
    t = np.array(d["where"]["frames"]["share_by_time"])
    assert t.shape[1] == 2 and np.all(np.diff(t[:, 0]) > 0)
    np.testing.assert_allclose(t[:, 1].sum(), 1.0, rtol=1e-9)
    rg = d["where"]["regime"]
    np.testing.assert_allclose(rg["tension"] + rg["compression"], 1.0)
    np.testing.assert_allclose(rg["elastic"] + rg["dissipative"], 1.0)
    names = [e["name"] for e in d["effects"]]
    assert set(names) <= set(VOCABULARY) and len(names) == len(set(names))
    assert set(d["verdict"]) <= set(VOCABULARY)
    for e in d["effects"]:
        assert 0 <= e["explained"] <= 1 and isinstance(e["score"], float)
        assert isinstance(e["parameters"], dict)
        assert set(e.get("confounded_with", [])) <= set(VOCABULARY)
    # evidence order among the simulated fits: no later fit beats an earlier one, i.e. has a
    # lower score and a residual lower by more than its discretisation credit plus the noise
    # tolerance (at most the noise rss)
    sim = [e for e in d["effects"] if e.get("simulated")]
    rss0, noise = d["floor"]["rss_train"], d["floor"]["rss_noise"]
    rss = {e["name"]: rss0 * (1 - e["explained"]) for e in sim}
    for i, a in enumerate(sim):
        for b in sim[i + 1:]:
            gain = rss[a["name"]] - rss[b["name"]]
            assert not (b["score"] < a["score"] and gain > b["discretisation_credit"] + noise), (a, b)


def test_cli_rejects_a_missing_scene(tmp_path, capsys):
    assert main(["diagnose", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "error" in capsys.readouterr().err
    # from Python too, before anything is written
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        diagnose(tmp_path / "nope.toml", tmp_path / "py")
    assert not (tmp_path / "py").exists() and not (tmp_path / "o").exists()


def test_report_is_self_contained_and_the_residual_map_is_readable(stiff):
    import meshio

    _, out = stiff
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 5
    assert "http://" not in page and "https://" not in page
    # the mesh's share of the gap is stated with the numbers of diagnosis.json
    d = json.loads((out / "diagnosis.json").read_text())["discretisation"]
    assert "<b>Mesh:</b>" in page and f"E x {d['stiffness_factor']:.3g}" in page
    assert f"max {d['gap_with_offset']['max_error_pct']:.2f} %" in page
    assert f"once-refined mesh (each tet split into 8) gives max {d['gap_refined_mesh']['max_error_pct']:.2f} %" in page
    # effect parameters as a person reads them: 4 significant digits, units named
    eff = json.loads((out / "diagnosis.json").read_text())["effects"]
    scale = next(e for e in eff if e["name"] == "stiffness_scale")["parameters"]["scale"]
    assert f"<td>scale {scale:.4g}, scale_range [" in page and repr(scale) not in page
    ray = next(e for e in eff if e["name"] == "rayleigh_damping")["parameters"]
    assert f"alpha_mass {ray['alpha_mass']:.4g} 1/s, alpha_stiffness {ray['alpha_stiffness']:.4g} s" in page
    m = meshio.read(out / "residual_map.vtu")
    share = m.cell_data["residual_share"][0]
    assert len(share) == len(m.cells_dict["tetra"])
    np.testing.assert_allclose(share.sum(), 1.0, rtol=1e-9)


def test_spacetime_control_forces_reach_beyond_the_marker_vertices(stiff):
    from matlearn.diagnosis import where
    from matlearn.diagnosis.problem import Problem

    _, out = stiff
    P = Problem(out.parent / "stiff" / "scene.toml")
    model = P.scene.model()
    rec = P.train[0]
    cf, src_c = where.residual_field(P, model, rec, "constrained")
    sf, src_s = where.residual_field(P, model, rec, "spacetime")
    assert (src_c, src_s) == ("constrained", "spacetime")
    on = lambda f: (np.abs(f.forces).sum(axis=2) > 0).sum(axis=1).mean()  # noqa: E731
    assert on(sf) > on(cf)
    # both see a stiffer truth: an elastic, not a dissipative residual
    for f in (cf, sf):
        assert where.regime_split(f)["elastic"] > 0.6
