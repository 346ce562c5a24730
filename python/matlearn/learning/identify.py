"""Does a learned model's stress level follow from its recordings? (`matlearn learn` checks it.)

Recordings fix a material's stress only relative to a known force. In a release, a flick or a
sag the inertia and the weight are that force: the motion's frequency and amplitude change with
the stress scale. A slowly driven object (the top cap of a sphere moved by keyframes) is close
to equilibrium between its clamp and the drive, whatever its stiffness, so its recordings leave
the stress scale free: a model learned from them reproduces motions of the same kind at any
scale, but not a motion under a known force (a load, gravity on another shape).

The check replays the train recordings with every stress of the learned model (elastic,
correction, stiffness-proportional damping) scaled by the factors of SCALE_GRID. With gravity as
the only external force this is exactly the model with its density divided by the factor (the
backward-Euler equations M a = s f_stress + M g and (M / s) a = f_stress + (M / s) g agree; the
mass-proportional damping and the drive points are unchanged), so it needs no new model code.
The scale counts as determined when the lowest train rms error lies inside the grid and every
factor at least 2x away from it raises the rms DETERMINED_RATIO times or more, and by at least
VISIBLE of the recordings' own motion (the rms marker displacement from where each marker is
first seen): noise-free data make even a 0.01 % change of a slowly driven motion a large ratio.
The rule is also applied to every recording on its own (its replay errors are in the same
simulations), so the message says which recordings carry the scale, and one that determines the
scale on its own, at the pooled errors' best factor, determines it for all: a slowly driven
recording adds its motion to the pooled VISIBLE bar but nothing to the errors' spread. Measured
on the learning table's models: their releases and flicks change by 0.25-2.2 times their motion
at x0.5 and x2, the two driven spheres by 0.05 at most, a slowly driven test bar by 0.003.
"""
from __future__ import annotations

import numpy as np

from ..parallel import pmap

SCALE_GRID = (0.25, 0.5, 2.0, 4.0)
DETERMINED_RATIO = 2.0
VISIBLE = 0.1


def with_stress_factor(material, f: float):
    """`material` whose every stress acts f times as strongly: its density divided by f (the
    module docstring: exact with gravity as the only external force)."""
    from dataclasses import replace

    if not f > 0:
        raise ValueError(f"stress_factor must be > 0, got {f}")
    rho = np.asarray(material.density, float) / f
    return replace(material, density=float(rho) if rho.ndim == 0 else rho)


def check_learned(scene, params, role: str = "train") -> dict:
    """stress_scale_check of `scene`'s own material and damping plus the correction `params`
    (RbfParams; None: no correction), as a learning run leaves them."""
    corr = params.correction() if params is not None else None
    return stress_scale_check(scene, lambda f: scene.model(corr, material=with_stress_factor(scene.material, f)),
                              role)


def _replay_rms(scene, model, role: str, count: int) -> tuple[float, list[float]]:
    """Pooled and per-recording rms marker error (% of the size) of the `role` replays (`count`
    recordings with markers); all inf when a replay fails (a scaled model that cannot be
    simulated is certainly not what the recordings show)."""
    from ..replay import score

    try:
        s = score(scene, model, role)
    except (RuntimeError, FloatingPointError):
        return float("inf"), [float("inf")] * count
    return float(s["rms_error_pct"]), [float(r["rms_error_pct"]) for r in s["recordings"]]


def _displacements(rec) -> np.ndarray:
    """Distances of a recording's seen marker samples from where each marker is first seen."""
    seen = rec.seen
    ref = rec.markers[np.argmax(seen, axis=0), np.arange(rec.num_markers)]
    return np.linalg.norm(rec.markers - ref[None], axis=2)[seen]


def _rms_pct(d: np.ndarray, size: float) -> float:
    """The rms of distances `d` in % of `size` (0 for none)."""
    return float(100.0 * np.sqrt(np.mean(d**2)) / size) if d.size else 0.0


def _marker_recordings(scene, role: str) -> list:
    """(file name, recording) of the `role` recordings with markers, as replay.score takes them."""
    return [(p.name, rec) for p, rec in zip(scene.recording_paths(role), scene.recordings_with_role(role))
            if rec.num_markers > 0]


def _motions(scene, recs: list, role: str) -> tuple[float, list[float]]:
    """(pooled, per recording) rms marker displacement (% of the size) of `recs` ((name,
    recording) pairs) from where each marker is first seen, over all seen samples."""
    d = [_displacements(rec) for _, rec in recs]
    if not any(x.size for x in d):
        raise ValueError(f"the scene has no '{role}' recording with seen markers")
    size = scene.object_size
    return _rms_pct(np.concatenate(d), size), [_rms_pct(x, size) for x in d]


def motion_rms(scene, role: str = "train") -> float:
    """The rms displacement (% of the object size) of the `role` recordings' markers from where
    each is first seen, over all seen samples."""
    return _motions(scene, _marker_recordings(scene, role), role)[0]


def _decide(fs: list, rms: list, motion: float) -> tuple[int, bool]:
    """(index of the lowest rms, determined): the module docstring's rule."""
    i = int(np.argmin(rms))
    best, low = fs[i], rms[i]
    far = [r for f, r in zip(fs, rms) if max(f / best, best / f) >= 2.0 - 1e-9]
    return i, bool(0 < i < len(fs) - 1 and all(r >= DETERMINED_RATIO * low and r - low >= VISIBLE * motion
                                               for r in far))


def stress_scale_check(scene, model_of, role: str = "train", factors=SCALE_GRID) -> dict:
    """How strongly the `role` recordings of `scene` fix the stress scale of a model.

    model_of(f): the model with every stress scaled by f (f = 1: as given), e.g.
    ``lambda f: scene.model(material=with_stress_factor(scene.material, f))``
    (check_learned). factors: the scales tried besides
    1 (at least one <= 0.5 and one >= 2).
    Returns dict(factors (sorted, 1 included), rms_error_pct (per factor, % of the object size),
    motion_rms_pct (motion_rms), best_factor (the lowest rms), determined, recordings (per
    recording with markers: file, rms_error_pct, motion_rms_pct, best_factor, determined, the same
    rule applied to that recording alone: which recordings carry the scale, for a user choosing
    what to record), message (one line for the user))."""
    fs = sorted({1.0, *(float(f) for f in factors)})
    if fs[0] <= 0 or fs[0] > 0.5 or fs[-1] < 2.0:
        raise ValueError(f"stress scale factors must be positive with one <= 0.5 and one >= 2, got {list(factors)}")
    recs = _marker_recordings(scene, role)
    motion, motions = _motions(scene, recs, role)
    # the factors' replays on the cores (matlearn.parallel; the same result)
    runs = pmap(lambda f: _replay_rms(scene, model_of(f), role, len(recs)), fs)
    rms = [r[0] for r in runs]
    if not np.isfinite(rms[fs.index(1.0)]):
        raise RuntimeError(f"the model cannot replay the {role} recordings")
    i, determined = _decide(fs, rms, motion)
    best, low = fs[i], rms[i]
    per = []
    for k, ((name, _), m_k) in enumerate(zip(recs, motions)):
        r_k = [run[1][k] for run in runs]
        j, det = _decide(fs, r_k, m_k)
        per.append({"file": name, "rms_error_pct": r_k, "motion_rms_pct": m_k, "best_factor": fs[j],
                    "determined": det})
    # a recording that fixes the scale on its own fixes it for all (where the pooled errors agree
    # on the factor): the pooled rule's VISIBLE bar grows with recordings that carry no scale
    determined = determined or any(p["determined"] and p["best_factor"] == best for p in per)
    fixing = [f"{p['file']} (x{p['best_factor']:g})" for p in per if p["determined"]]
    free = [p["file"] for p in per if not p["determined"]]

    def said(files, one, each):
        return f"{files[0]} {one}" if len(files) == 1 else f"{', '.join(files)} each {each}"

    if len(per) < 2:
        which = ""
    elif fixing and free:
        which = f"; on its own {said(fixing, 'determines', 'determine')} it, {said(free, 'leaves', 'leave')} it free"
    elif fixing:
        which = "; every recording on its own determines it"
    else:
        which = "; no recording on its own determines it"
    shown = ", ".join(f"x{f:g}: {r:.3g} %" for f, r in zip(fs, rms))
    if determined and best == 1.0:
        message = f"the {role} recordings determine the stress scale ({role} rms error {shown}{which})"
    elif determined:
        message = (f"the {role} recordings determine a stress scale {best:g} times the model's, not the "
                   f"model's own ({role} rms error {shown}{which})")
    else:
        near = [f for f, r in zip(fs, rms) if r < DETERMINED_RATIO * low or r - low < VISIBLE * motion]
        span = f"x{near[0]:g}" + (" or less" if near[0] == fs[0] else "")
        span += f" to x{near[-1]:g}" + (" or more" if near[-1] == fs[-1] else "")
        if near[0] != fs[0] and near[-1] != fs[-1]:  # bounded: a weak, not a missing, determination
            lead = (f"the {role} recordings fix the stress scale only loosely: every stress scaled from {span} "
                    f"keeps the {role} rms error near its lowest, which is at x{best:g}")
        else:
            lead = (f"the {role} recordings do not determine the stress scale: with every stress scaled "
                    f"from {span} the {role} rms error stays near its lowest")
        message = (f"{lead} ({shown}; the recorded motion itself: {motion:.3g} %{which}). The model reproduces "
                   f"motions like these, but under a known force (a load, a release, gravity on another shape) "
                   f"its stiffness may be off by such a factor; a recording with a known force (a release from "
                   f"a held load, over a few oscillations; a sag) fixes it")
    return {"factors": fs, "rms_error_pct": rms, "motion_rms_pct": motion, "best_factor": best,
            "determined": bool(determined), "recordings": per, "message": message}
