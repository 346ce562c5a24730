"""Transfer (issue 3, item 10): a correction learned on one object, applied to other shapes and
meshes of the same material, closes most of their nominal gap there. The learner sees only the
small bar's recordings; the other objects' recordings are made with the same hidden truth
(neo-Hookean, E = 2e5 Pa) and scored against the same nominal guess (co-rotated, 3.5e5 Pa)."""
import json

import numpy as np
import pytest

from matlearn import cli, meshes
from matlearn.learning import transfer_score
from matlearn.materials import Damping, Material
from matlearn.scene import load_scene
from matlearn.synthetic import Motion, make_case

from learning_cases import small_bar_case

TRUTH = (Material("neo_hookean", 2e5, 0.43, 1000.0), Damping(0.0, 0.004))
NOMINAL = (Material("corotated", 3.5e5, 0.43, 1000.0), Damping(0.0, 0.004))


def other_object(folder, name, mesh, clamp_depth):
    """A case on `mesh` (clamped within clamp_depth of its -x end) with two held-out releases of
    tip loads that the training never applied."""
    V = np.asarray(mesh.vertices)
    x0, x1 = V[:, 0].min(), V[:, 0].max()
    tip = [[x1 - 0.125 * (x1 - x0), -1, -1], [1, 1, 1]]
    motions = [Motion("release", "test", 0.1, load={"box": tip, "force": [0, 0.35, 0.1]}),
               Motion("release", "test", 0.1, load={"box": tip, "force": [0, -0.2, 0.3]})]
    return make_case(folder, name, mesh, *TRUTH, mesh, *NOMINAL, [[-1, -1, -1], [x0 + clamp_depth, 1, 1]],
                     motions, marker_fraction=0.5, seed=4)


@pytest.fixture(scope="module")
def learned_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("transfer")
    case = small_bar_case(root / "cases")
    run = root / "run"
    assert cli.main(["learn", str(case), "--out", str(run), "--iterations", "2", "--modes", "12",
                     "--centers", "12", "--no-distill", "--quiet"]) == 0
    # releases from held loads fix the stress scale: the model may be used on other objects
    assert json.loads((run / "model.json").read_text())["stress_scale_determined"] is True
    return root, load_scene(case), run


@pytest.mark.parametrize("shape", ["thick_bar", "capsule"])
def test_a_learned_correction_transfers_to_another_shape_and_mesh(learned_run, shape):
    root, source, run = learned_run
    if shape == "thick_bar":  # shorter, wider, 4 x 2 x 1 cells instead of 5 x 1 x 1
        mesh, depth = meshes.bar(0.06, 0.025, 0.02, cells=(4, 2, 1)), 1e-4
    else:  # a TetGen capsule: curved surface, ~30x the source's tets
        mesh, depth = meshes.capsule(radius=0.011, length=0.06, max_volume=(0.011 / 1.5) ** 3), 0.006
    scene = load_scene(other_object(root / "other", shape, mesh, depth))
    assert scene.mesh.num_tets != source.mesh.num_tets
    r = transfer_score(scene, run_dir=run)
    nominal, learned = r["nominal"]["max_error_pct"], r["learned"]["max_error_pct"]
    print(shape, scene.mesh.num_tets, "tets: nominal", nominal, "learned", learned)
    assert nominal > 1.0  # the nominal guess is visibly wrong on this object too
    # Stated factor: the transferred model cuts the held-out max error at least 5x on both
    # objects (measured 12x on the thick bar, 17x on the capsule).
    assert learned < nominal / 5, (nominal, learned)
    for rec_n, rec_l in zip(r["nominal"]["recordings"], r["learned"]["recordings"]):
        assert rec_l["max_error_pct"] < rec_n["max_error_pct"]


def test_transfer_score_needs_one_model(learned_run):
    _, source, run = learned_run
    with pytest.raises(ValueError, match="exactly one"):
        transfer_score(source)
    with pytest.raises(ValueError, match="exactly one"):
        transfer_score(source, correction=object(), run_dir=run)
