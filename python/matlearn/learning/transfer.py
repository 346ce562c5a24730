"""Transfer: apply a correction learned on one object to another mesh/shape of the same material
and score it on that object's recordings (the correction acts on principal stretches and
rates, so it does not depend on the mesh)."""
from __future__ import annotations

from ..replay import score


def transfer_score(scene, correction, role: str = "test") -> dict:
    """Errors of `scene`'s nominal model and of nominal + `correction` on its `role` recordings:
    dict(nominal=..., learned=...), each with max_error_pct / rms_error_pct (% of size)."""
    return {"nominal": score(scene, scene.model(), role), "learned": score(scene, scene.model(correction), role)}
