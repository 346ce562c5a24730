"""The stiffness-field start (learning/field.py, start "field"): a per-element Young's modulus fitted
on top of the baseline to the train recordings, for objects whose stiffness varies in space."""
import json

import numpy as np
import pytest

from matlearn import cli, meshes
from matlearn.learning import field as field_mod
from matlearn.learning import start as start_mod
from matlearn.learning.io import scene_model
from matlearn.materials import Damping, Material
from matlearn.replay import score
from matlearn.scene import load_scene
from matlearn.synthetic import Motion, make_case

L = 0.08  # bar length (m)


def _bar_case(folder, name="bar2", cells=(4, 1, 2)):
    """A two-layer cantilever: the top half of its thickness (z > 0) 8x stiffer than the bottom
    (truth on the model's own mesh); the nominal model is homogeneous. Train: a tip load
    released in y (along the layers) and a released twist; test: a tip load released in z
    (across the layers), a motion the training never shows. No homogeneous modulus fits both
    bending directions of a bi-layer."""
    mesh = meshes.bar(L, 0.02, 0.02, cells=cells)
    V = np.asarray(mesh.vertices)
    centroid_z = V[np.asarray(mesh.tets)].mean(axis=1)[:, 2]
    E = np.where(centroid_z > 0, 8e5, 1e5)
    tip = [[L - 0.011, -1, -1], [1, 1, 1]]
    motions = [Motion("release", "train", 0.1, load={"box": tip, "force": [0, 0.2, 0.0]}),
               Motion("release", "train", 0.1, twist={"box": tip, "torque": [0.002, 0, 0]}),
               Motion("release", "test", 0.1, load={"box": tip, "force": [0, 0.0, 0.2]})]
    return make_case(folder, name, mesh, Material("corotated", E, 0.4, 1000.0), Damping(0.0, 0.004),
                     mesh, Material("corotated", 4e5, 0.4, 1000.0), Damping(0.0, 0.004),
                     [[-1, -1, -1], [1e-4, 1, 1]], motions, marker_fraction=1.0, seed=2)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    return _bar_case(tmp_path_factory.mktemp("field"))


def test_face_pairs_match_a_brute_force_search():
    mesh = meshes.bar(0.03, 0.01, 0.01, cells=(3, 1, 1))
    tets = np.asarray(mesh.tets)
    got = {tuple(p) for p in field_mod.face_pairs(tets)}
    faces = [{frozenset(t[list(f)]) for f in ([0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3])} for t in tets]
    want = {(a, b) for a in range(len(tets)) for b in range(a + 1, len(tets)) if faces[a] & faces[b]}
    assert got == want and len(got) == len(field_mod.face_pairs(tets))
    # k-means patches: every tet labelled, adjacent patch pairs only between distinct patches
    labels = field_mod.patches(mesh, 4, seed=0)
    assert labels.shape == (len(tets),) and set(labels) == set(range(labels.max() + 1))
    pp = field_mod.patch_pairs(tets, labels)
    assert np.all(pp[:, 0] < pp[:, 1])
    assert np.array_equal(field_mod.patches(mesh, 100), np.arange(len(tets)))


def test_field_recovers_a_stiffer_half_and_predicts_the_held_out_motion(case, tmp_path):
    sc = load_scene(case)
    lscene, info = start_mod.field_start(sc, tmp_path / "run", max_evaluations=10)
    E = np.asarray(lscene.material.youngs_modulus)
    V = np.asarray(sc.mesh.vertices)
    z = V[np.asarray(sc.mesh.tets)].mean(axis=1)[:, 2]
    contrast = np.mean(np.log(E[z > 0])) - np.mean(np.log(E[z < 0]))
    # truth: log(8e5 / 1e5) = 2.08; the homogeneous baseline holds none (smoothing shrinks it)
    assert 0.7 < contrast < 2.5, contrast
    f = info["field"]
    assert f["train_rms_pct"] < 0.3 * f["train_rms_pct_before"], f
    base = sc.model(material=start_mod.material_from_dict(info["baseline_material"]),
                    damping=lscene.damping)
    field = sc.model(material=lscene.material, damping=lscene.damping)
    err_base = score(sc, base, "test")["max_error_pct"]
    err_field = score(sc, field, "test")["max_error_pct"]
    # the held-out motion bends across the layers, which no homogeneous modulus matches along
    # them too: the field carries over (measured 0.27 -> 0.05 % of the size)
    assert err_field < 0.5 * err_base, (err_field, err_base)
    # cached: a resumed run does not fit again
    again, info2 = start_mod.field_start(sc, tmp_path / "run")
    assert info2["material"] == info["material"]


def test_tangent_jacobian_matches_finite_differences_of_the_simulated_residual(case):
    """The field fit's Jacobian (forward-mode tangents of the linearised replay, one pass for all
    patches) against central differences of the objective itself, full-Newton simulations."""
    from matlearn.embedding import embed_points
    from matlearn.learning.baseline import marker_residual_pct

    sc = load_scene(case)
    labels = field_mod.patches(sc.mesh, 4, seed=0)
    recs = sc.recordings_with_role("train")
    embs = [embed_points(sc.mesh, r.marker_rest) for r in recs]
    E0 = np.full(sc.mesh.num_tets, 3e5) * np.exp(0.2 * np.sin(np.arange(sc.mesh.num_tets)))

    def material(q):
        return Material("corotated", E0 * np.exp(q[labels]), 0.4, 1000.0)

    def residual(q):
        return marker_residual_pct(sc, sc.model(material=material(q), damping=sc.damping), recs, embs)

    r0 = residual(np.zeros(4))
    J = field_mod.TangentJacobian(sc, sc.damping, labels)(material(np.zeros(4)), len(r0))
    assert J is not None and J.shape == (len(r0), 4)
    h = 1e-3
    for j in range(4):
        e = np.eye(4)[j] * h
        fd = (residual(e) - residual(-e)) / (2 * h)
        assert np.linalg.norm(J[:, j] - fd) < 0.1 * np.linalg.norm(fd), (j, np.linalg.norm(J[:, j] - fd) / np.linalg.norm(fd))
    # a layout that does not match the objective's rows: no Jacobian (the fit then differences)
    assert field_mod.TangentJacobian(sc, sc.damping, labels)(material(np.zeros(4)), len(r0) + 3) is None


def test_tangent_and_finite_difference_fits_agree(case):
    """The tangent fit reaches the finite-difference fit's field with a fraction of the
    simulations (measured: contrast 0.431 vs 0.431, train rms 0.146 -> 0.01276 vs 0.01275 %,
    6 vs 393 simulations)."""
    sc = load_scene(case)
    base = Material("corotated", 3e5, 0.4, 1000.0)
    z = np.asarray(sc.mesh.vertices)[np.asarray(sc.mesh.tets)].mean(axis=1)[:, 2]
    got = {}
    for jacobian in ("tangent", "fd"):
        mat, info = field_mod.fit_stiffness_field(sc, base, sc.damping, iterations=8, jacobian=jacobian)
        logE = np.log(np.asarray(mat.youngs_modulus))
        got[jacobian] = (logE[z > 0].mean() - logE[z < 0].mean(), info)
        assert info["jacobian"] == jacobian
        # truth 8e5 above z = 0, 1e5 below (log contrast 2.08; the smoothing shrinks it)
        assert got[jacobian][0] > 0.3, info
        assert info["train_rms_pct"] < 0.2 * info["train_rms_pct_before"], info
    (ct, it), (cf, if_) = got["tangent"], got["fd"]
    assert abs(ct - cf) < 0.05, (ct, cf)
    assert it["train_rms_pct"] < 1.05 * if_["train_rms_pct"], (it, if_)
    assert it["simulations"] < 0.1 * if_["simulations"], (it, if_)


def test_a_killed_field_fit_resumes_on_the_same_path(case, tmp_path):
    sc = load_scene(case)
    base = Material("corotated", 3e5, 0.4, 1000.0)
    kw = dict(iterations=4, max_patches=8)
    whole, info = field_mod.fit_stiffness_field(sc, base, sc.damping, **kw)
    ck = tmp_path / "field_checkpoint.json"
    # "killed" after two iterations: the checkpoint holds iteration 2's state
    field_mod.fit_stiffness_field(sc, base, sc.damping, iterations=2, max_patches=8, checkpoint=ck)
    assert json.loads(ck.read_text())["iteration"] == 2
    said = []
    resumed, info2 = field_mod.fit_stiffness_field(sc, base, sc.damping, checkpoint=ck, log=said.append, **kw)
    assert any("resumed after iteration 2" in m for m in said)
    np.testing.assert_array_equal(resumed.youngs_modulus, whole.youngs_modulus)
    assert info2["simulations"] < info["simulations"] + 2  # iterations 1-2 were not run again
    # a checkpoint of another fit (other base modulus) is ignored
    other, _ = field_mod.fit_stiffness_field(sc, Material("corotated", 2e5, 0.4, 1000.0), sc.damping,
                                             checkpoint=ck, log=said.append, **kw)
    assert sum("resumed" in m for m in said) == 1


def test_cli_field_start_applies_the_field_on_its_mesh_only(case, tmp_path):
    out = tmp_path / "run"
    assert cli.main(["learn", str(case), "--out", str(out), "--iterations", "1", "--modes", "10",
                     "--centers", "8", "--no-distill", "--quiet", "--start", "field"]) == 0
    meta = json.loads((out / "model.json").read_text())
    assert meta["start"] == "field" and len(meta["base_material"]["youngs_modulus"]) == load_scene(case).mesh.num_tets
    sc = load_scene(case)
    E_here = np.asarray(scene_model(sc, out).mu)
    assert np.ptp(np.log(E_here)) > 0.5  # per element on its own mesh
    # another mesh of the same object (finer): the field's volume-weighted log-mean modulus
    other = load_scene(_bar_case(tmp_path / "other", "bar3", cells=(6, 1, 1)))
    mu_other = np.asarray(scene_model(other, out).mu)
    E_h = meta["base_material_homogeneous"]["youngs_modulus"]
    nu = meta["base_material_homogeneous"]["poisson_ratio"]
    assert np.allclose(mu_other, E_h / (2 * (1 + nu)), rtol=1e-12)


def test_a_best_run_that_kept_a_field_gives_other_meshes_its_homogeneous_model(case, tmp_path):
    """io.scene_model: on the field's own mesh the field model; on another mesh the model named by
    `transfer_model` (the best homogeneous start's), not the field's log-mean."""
    from matlearn.learning.io import save_model

    sc = load_scene(case)
    other = load_scene(_bar_case(tmp_path / "other", "bar3", cells=(6, 1, 1)))
    nt = sc.mesh.num_tets
    field_mat = Material("corotated", 4e5 * np.exp(0.5 * np.sin(np.arange(nt))), 0.4, 1000.0)
    run = tmp_path / "run"
    field_info = {"material": start_mod.spec_dict(field_mat), "damping": start_mod.spec_dict(sc.damping),
                  "material_homogeneous": start_mod.spec_dict(field_mod.homogeneous(field_mat, sc.mesh.rest_volumes)),
                  "material_mesh": field_mod.mesh_fingerprint(sc.mesh), "transfer_start": "baseline"}
    base_info = {"material": start_mod.spec_dict(Material("corotated", 2.5e5, 0.4, 1000.0)),
                 "damping": start_mod.spec_dict(sc.damping)}
    save_model(run / "start_baseline", start_mod.zero_params(), meta=start_mod.model_meta(base_info))
    save_model(run, start_mod.zero_params(), meta={"start": "best", **start_mod.model_meta(field_info)})
    assert json.loads((run / "model.json").read_text())["transfer_model"] == "start_baseline"
    mu_here = np.asarray(scene_model(sc, run).mu)
    np.testing.assert_allclose(mu_here, field_mat.youngs_modulus / (2 * 1.4), rtol=1e-12)
    mu_other = np.asarray(scene_model(other, run).mu)
    np.testing.assert_allclose(mu_other, 2.5e5 / (2 * 1.4), rtol=1e-12)
    # without a transfer model (a `--start field` run): the field's log-mean
    save_model(run, start_mod.zero_params(), meta={"start": "field", **start_mod.model_meta(
        {k: v for k, v in field_info.items() if k != "transfer_start"})})
    E_h = field_info["material_homogeneous"]["youngs_modulus"]
    np.testing.assert_allclose(np.asarray(scene_model(other, run).mu), E_h / (2 * 1.4), rtol=1e-12)


def test_diagnose_suggests_the_field_start_when_the_stiffness_varies_in_space():
    from matlearn.commands.diagnose import learning_hint

    region = {"verdict": ["heterogeneity"], "effects": [{"name": "heterogeneity"}]}
    assert "--start field" in learning_hint(region, "s.toml")
    tied = {"verdict": ["stiffness_scale"],
            "effects": [{"name": "stiffness_scale", "confounded_with": ["density", "heterogeneity"]},
                        {"name": "heterogeneity"}]}
    assert "--start field" in learning_hint(tied, "s.toml")
    # a uniform change, or nothing found: no field to learn
    assert learning_hint({"verdict": ["stiffness_scale"], "effects": [{"name": "stiffness_scale",
                                                                      "confounded_with": ["density"]}]}, "s") is None
    assert learning_hint({"verdict": [], "effects": [{"name": "heterogeneity"}]}, "s") is None
