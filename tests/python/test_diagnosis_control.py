"""A control case (truth = nominal material on a finer mesh) yields verdict []: the
discretisation gap alone is not reported as an effect."""
import numpy as np

from matlearn.diagnosis import diagnose

from diagnosis_cases import FAST, L, tiny_case


def test_control_case_claims_no_effect(tmp_path):
    scene = tiny_case(tmp_path, "control", E_scale=1.0, seed=3)
    result = diagnose(scene, tmp_path / "out", progress=lambda m: None, **FAST)
    assert result["verdict"] == []
    # the raw gap is not zero (coarse mesh), it is within the estimated floor
    assert result["gap_before"]["max_error_pct"] > 0
    assert result["floor"]["rss_train"] < 2.5 * result["floor"]["rss_floor"]
    # and the result says so: the coarse mesh is too stiff, and with only the stiffness factor
    # it takes (inside its range) the held-out gap shrinks by most of itself (5.6 -> 0.65 %)
    d = result["discretisation"]
    assert d["refined_mesh_factor"] < 0.9 and d["factor_range"][0] <= d["stiffness_factor"] <= d["factor_range"][1]
    assert d["gap_with_offset"]["max_error_pct"] < 0.3 * result["gap_before"]["max_error_pct"]
    # the nominal material on the once-refined mesh, closer to the finer truth, also shrinks it
    assert d["gap_refined_mesh"]["max_error_pct"] < 0.5 * result["gap_before"]["max_error_pct"]


def test_truth_on_the_model_mesh_claims_no_effect(tmp_path):
    """Recordings the nominal model on its own mesh matches within the noise hold no gap: the
    discretisation correction (which assumes a finer truth) must not invent a stiffness effect."""
    scene = tiny_case(tmp_path, "same_mesh", E_scale=1.0, seed=3, refine=1, noise=3e-5)
    result = diagnose(scene, tmp_path / "out", progress=lambda m: None, **FAST)
    floor = result["floor"]
    assert floor["rss_nominal_raw"] < 1.5 * floor["rss_noise"]
    assert floor["rss_train"] > 10 * floor["rss_floor"]  # the corrected baseline alone would claim
    assert result["verdict"] == []
    # here the truth *is* the model's mesh: the once-refined mesh moves away from it
    d = result["discretisation"]
    assert d["gap_refined_mesh"]["max_error_pct"] > 2 * result["gap_before"]["max_error_pct"]


def test_box_clamp_cutting_the_mesh_claims_no_effect(tmp_path):
    """A box clamp whose face cuts the model's first layer of tets, and neither the model's nor
    its once-refined mesh's vertices lie in the cut part: a finer body is held over more of it
    (here, the extreme, over the whole first layer) and is stiffer near the clamp. That is the
    clamp's discretisation, not an effect: verdict [] with the hold reported (the cut tets
    stiffened inside the bound that holding all their vertices gives). Before: heterogeneity at
    the clamp, train rss 1.86 against a floor of 0.002."""
    h = L / 5
    scene = tiny_case(tmp_path, "cut_clamp", seed=3, clamp_x=0.4 * h, truth_clamp_x=1.01 * h)
    result = diagnose(scene, tmp_path / "out", progress=lambda m: None, **FAST)
    cf = result["discretisation"]["clamp_footprint"]
    assert cf["cut_tets"] == 24 and cf["vertices_of_cut_tets"] == 9
    assert 2.0 < cf["cut_stiffness_factor"] <= cf["cut_stiffness_range"][1]
    assert result["verdict"] == []
    assert result["floor"]["rss_train"] < 10 * result["floor"]["rss_floor"]
    # a box ending at the body's face cuts nothing: no hold reported
    face = diagnose(tiny_case(tmp_path, "face_clamp", seed=3), tmp_path / "out2", progress=lambda m: None, **FAST)
    assert "clamp_footprint" not in face["discretisation"]


def test_box_cut_vertices():
    """The vertices of the tets a box cuts (part of their volume inside it), not those a box
    ending at the body's face touches."""
    from matlearn import meshes
    from matlearn.diagnosis.discretisation import box_cut_tets, box_cut_vertices

    bar = meshes.bar(1.0, 0.2, 0.2, (5, 1, 1))
    V, T = np.asarray(bar.vertices), np.asarray(bar.tets)
    at_face = np.flatnonzero(V[:, 0] <= 1e-9)
    assert len(box_cut_vertices(V, T, [[-1, -1, -1], [1e-9, 1, 1]], at_face)) == 0
    cut = box_cut_vertices(V, T, [[-1, -1, -1], [0.05, 1, 1]], at_face)
    assert set(np.round(V[cut, 0], 6)) == {0.2}  # the first layer's far vertices
    assert box_cut_tets(V, T, [[-1, -1, -1], [0.05, 1, 1]]).sum() == 6  # the first layer's 6 tets
    assert len(box_cut_vertices(V, T, [[-1, -1, -1], [0.25, 1, 1]], np.flatnonzero(V[:, 0] <= 0.25))) > 0
