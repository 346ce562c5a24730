"""The start decision of the diagnosis (problem.start_in_motion) as it was until session 27 (the
marker velocity over a fixed 7 frames) and as it is now (over a quarter of the nominal model's
lowest period, problem.velocity_frames), on every recording of the given scenes that is not
declared at rest and has no driven points. Prints one line per recording and "CHANGED" where the
two decide differently.

    python bench/start_window_check.py WORK/*/scene.toml
"""
from __future__ import annotations

import os
import sys

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
from matlearn.diagnosis import problem as prob  # noqa: E402


def decide(P, rec, old: bool) -> dict:
    """start_in_motion's info; old: over 7 frames, and "moving" by the rule before session 27
    (half the rest start's residual above the noise removed, without the out-of-window check)."""
    info = prob.start_in_motion(P, rec, frames=7 if old else None)[1]
    if old and "rss_moving" in info:
        rest, moving = info["rss_rest"], info["rss_moving"]
        info["moving"] = bool(rest - moving >= prob.START_EXPLAINED * max(rest - info["rss_noise"], 0.0)
                              and moving < rest)
    return info


def main(scenes) -> int:
    changed = total = 0
    for scene in scenes:
        P = prob.Problem(scene, estimate_velocity=False)
        for role, recs in (("train", P.train), ("test", P.test)):
            for i, rec in enumerate(recs):
                if rec.at_rest_initially or rec.has_drive:
                    continue
                a, b = decide(P, rec, True), decide(P, rec, False)
                key = ["moving" if d["moving"] else "rest" for d in (a, b)]
                diff = key[0] != key[1]
                changed, total = changed + diff, total + 1
                rss = {k: round(v, 5) for k, v in b.items() if k.startswith("rss")}
                print(f"{scene} {role} {i}: {prob.velocity_frames(rec, P.nominal_omega())} frames, "
                      f"{key[0]} -> {key[1]} {rss} (before: {a.get('rss_moving', '-')})"
                      f"{'  CHANGED' if diff else ''}", flush=True)
    print(f"{changed} of {total} recordings decided differently")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
