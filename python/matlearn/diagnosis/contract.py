"""diagnosis.json's public contract (../shared/docs/formats.md), enforced on the result before it
is written, so that a consumer that reads the documented keys never meets a null or a
non-standard number:

* every effect's `gap_after` is {"max_error_pct", "rms_error_pct"} with finite numbers. A fitted
  model that cannot be simulated on a held-out motion (e.g. a stress polynomial fitted on the
  train strains that loses stability at the larger strains of a held-out motion: the held
  pose's static solve is not positive definite) has no gap; it is reported as an error of one
  object size (100 %, the convention of a failed simulation in `problem.stack_residuals`) and
  the effect carries `held_out_failed: true`;
* the file is strict JSON: a non-finite number (NaN, Infinity) anywhere is an error of the
  diagnosis, written as null and listed in the result's `nonfinite` key (never silently as the
  non-standard tokens NaN / Infinity that `json.dump` writes by default).
"""
from __future__ import annotations

import json
import math

import numpy as np

FAILED_GAP_PCT = 100.0  # a held-out motion the fitted model cannot simulate: one object size


def _is_gap(g) -> bool:
    return isinstance(g, dict) and all(
        isinstance(g.get(k), (int, float)) and not isinstance(g.get(k), bool) and math.isfinite(g[k])
        for k in ("max_error_pct", "rms_error_pct"))


def _finite(x, path, bad):
    """x with numpy scalars/arrays turned into plain Python values and non-finite floats into
    None (their paths appended to `bad`)."""
    if isinstance(x, dict):
        return {str(k): _finite(v, f"{path}.{k}", bad) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_finite(v, f"{path}[{i}]", bad) for i, v in enumerate(list(x))]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        if not math.isfinite(float(x)):
            bad.append(path)
            return None
        return float(x)
    return x


def conform(result: dict) -> dict:
    """The result made to follow formats.md (see the module docstring); returns it."""
    bad = []
    clean = _finite(result, "", bad)
    result.clear()
    result.update(clean)
    for e in result.get("effects", []):
        if not _is_gap(e.get("gap_after")):
            e["gap_after"] = {"max_error_pct": FAILED_GAP_PCT, "rms_error_pct": FAILED_GAP_PCT}
            e["held_out_failed"] = True
    if not _is_gap(result.get("gap_before")):
        result["gap_before"] = {"max_error_pct": FAILED_GAP_PCT, "rms_error_pct": FAILED_GAP_PCT}
        result["held_out_failed"] = True
    if bad:
        result["nonfinite"] = [b.lstrip(".") for b in bad]
    return result


def write(result: dict, path) -> dict:
    """conform(result) written to `path` as strict JSON; returns the result."""
    conform(result)
    with open(path, "w") as f:
        json.dump(result, f, indent=1, allow_nan=False)
    return result
