"""A soft region of the truth is attributed to heterogeneity and located (IoU with the model
elements inside the true region)."""
from matlearn.diagnosis import diagnose

from diagnosis_cases import FAST, model_region, tiny_case

REGION = (0.3, 0.7)  # away from the clamp (not a support effect)


def test_soft_region_is_located(tmp_path):
    scene = tiny_case(tmp_path, "region", region=REGION, region_scale=0.35, seed=5)
    result = diagnose(scene, tmp_path / "out", progress=lambda m: None, **FAST)
    assert "heterogeneity" in result["verdict"][:2]
    first = set(result["where"]["regions"][0]["elements"])
    true = set(model_region(REGION).tolist())
    iou = len(first & true) / len(first | true)
    assert iou >= 0.6, (sorted(first), sorted(true))
