"""Scoring helpers shared by the diagnosis benches (they read only diagnosis.json, the public
output, and the bench rows)."""
from __future__ import annotations

import numpy as np


def refined_mesh_gap(result: dict):
    """The held-out gap of the nominal material on the once-refined model mesh (diagnosis.json's
    discretisation.gap_refined_mesh, % of the size): what a finer mesh alone would leave."""
    g = (result.get("discretisation") or {}).get("gap_refined_mesh")
    return g["max_error_pct"] if g else None


def median_refined_shrink(rows):
    """Median shrink of the held-out gap that the once-refined mesh alone gives, over the rows
    with a true effect (context for median_gap_shrink: how much of the gap is the model mesh's)."""
    got = [1 - r["gap_refined_mesh_pct"] / r["gap_before_pct"] for r in rows
           if r["true_effects"] and r.get("gap_refined_mesh_pct") is not None and r["gap_before_pct"]]
    return float(np.median(got)) if got else None
