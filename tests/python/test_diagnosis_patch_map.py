"""Locating a stiffer/softer region from the per-patch stiffness map fitted on simulations
(region.patch_map + region.split_patches) instead of a linearisation at the baseline."""
import numpy as np

from matlearn.diagnosis import fitting, region
from matlearn.diagnosis.effects import EffectContext
from matlearn.diagnosis.problem import Problem

from diagnosis_cases import model_region, tiny_case


def test_split_is_not_decided_by_strongly_loaded_patches_and_region_departs_from_baseline():
    rng = np.random.default_rng(0)
    theta = np.where(np.isin(np.arange(10), [2, 3, 4]), -1.0, 0.0) + 0.05 * rng.standard_normal(10)
    precision = np.full(10, 1.0)
    theta[[0, 1]] = [0.45, 0.35]  # strongly loaded (clamp side), off by their own mesh error
    precision[[0, 1]] = 400.0
    H = np.diag(precision)
    sel, (a, b) = region.split_patches(theta, H, np.ones(10))
    assert sorted(np.flatnonzero(sel)) == [2, 3, 4]
    assert a == np.clip(a, -1.1, -0.9) and b > -0.1
    # the same map with the region's sign flipped: still the three patches
    sel, (a, b) = region.split_patches(-theta, H, np.ones(10))
    assert sorted(np.flatnonzero(sel)) == [2, 3, 4] and a > 0.9


def test_patch_map_locates_a_soft_region_better_than_the_baseline_linearisation(tmp_path):
    """A soft (x0.5) band in the middle of a bar bent far (the baseline residual is ~13 in
    object-size units): the per-patch secants at the baseline put the region elsewhere (IoU
    0.07), the map fitted on simulations finds most of it."""
    cells = (8, 2, 2)
    true_region = (0.3, 0.6)
    scene = tiny_case(tmp_path, "pm", region=true_region, region_scale=0.5, seed=1, cells=cells)
    P = Problem(scene)
    s = P.scene
    ctx = EffectContext(s.mesh, s.material, s.damping, s.fixed)
    labels = fitting.make_patches(s.mesh, 8, seed=0)
    true = np.zeros(s.mesh.num_tets, bool)
    true[model_region(true_region, cells)] = True

    def iou(sel):
        found = np.isin(labels, np.flatnonzero(sel))
        return (found & true).sum() / (found | true).sum()

    r0 = fitting.residual_of(P, ctx, {})
    theta, rss, H = region.patch_map(P, ctx, labels)
    assert rss < 0.05 * float(r0 @ r0)
    vols = np.bincount(labels, weights=np.asarray(s.mesh.rest_volumes))
    sel, (a, b) = region.split_patches(theta, H, vols)
    Jp = np.zeros((len(r0), labels.max() + 1))
    for p in range(labels.max() + 1):
        ctx.region = labels == p
        Jp[:, p] = (fitting.residual_of(P, ctx, {"heterogeneity": [0.1, 0.0]}) - r0) / 0.1
    sel_lin, _ = fitting.locate_region(Jp, r0)
    # The 8-patch map of this tiny bar is ill-conditioned: which local optimum its fit reaches
    # depends on round-off (an Intel machine: map well ahead of the secants' 0.07; AMD EPYC,
    # session 10: map 0.44 against 0.27, patch 0 found, patch 4 left at the baseline).
    assert iou(sel) >= 0.35 and iou(sel) >= iou(sel_lin) + 0.1, (iou(sel), iou(sel_lin))
    assert a < b - 0.5  # softer than the rest
