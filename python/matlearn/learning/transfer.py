"""Transfer: apply a correction learned on one object to another mesh/shape of the same material
and score it on that object's recordings (the correction acts on principal stretches and
rates, so it does not depend on the mesh).

A learned model is its start material and damping (the scene's nominal ones, or the parameters
fitted first when the run started from the baseline: io.scene_model) plus the correction; it is
rebuilt on the other scene's mesh from a run folder written by `matlearn learn` (`run_dir`), or
a bare correction is added to the other scene's nominal model (`correction`)."""
from __future__ import annotations

from ..replay import score


def transfer_score(scene, correction=None, role: str = "test", run_dir=None, kind: str | None = None) -> dict:
    """Errors of `scene`'s nominal model and of the learned one on its `role` recordings:
    dict(nominal=..., learned=...), each with max_error_pct / rms_error_pct (% of size) and
    per-recording errors. The learned model: the run `run_dir` rebuilt on `scene` (its start
    material and damping + its correction, `kind` "rbf" / "mlp" / None: the run's choice), or
    `scene`'s nominal model + `correction`. Exactly one of the two must be given."""
    if (correction is None) == (run_dir is None):
        raise ValueError("transfer_score needs exactly one of `correction` and `run_dir`")
    if run_dir is not None:
        from .io import scene_model

        learned = scene_model(scene, run_dir, kind)
    else:
        learned = scene.model(correction)
    return {"nominal": score(scene, scene.model(), role), "learned": score(scene, learned, role)}
