"""The start decision of the diagnosis (problem.start_in_motion) with the old fixed 7-frame
velocity window and with the quarter-period window (problem.velocity_frames), on every recording
of the given scenes that is not declared at rest and has no driven points (session 27). Prints
one line per recording and "FLIP" where the two decide differently.

    python bench/start_window_check.py WORK/*/scene.toml
"""
from __future__ import annotations

import os
import sys

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
from matlearn.diagnosis.problem import Problem, start_in_motion, velocity_frames  # noqa: E402


def main(scenes) -> int:
    flips = total = 0
    for scene in scenes:
        P = Problem(scene, estimate_velocity=False)
        w = P.nominal_omega()
        for role, recs in (("train", P.train), ("test", P.test)):
            for i, rec in enumerate(recs):
                if rec.at_rest_initially or rec.has_drive:
                    continue
                n = velocity_frames(rec, w)
                old = start_in_motion(P, rec, frames=7)[1]
                new = old if n == 7 else start_in_motion(P, rec, frames=n)[1]
                flip = old["moving"] != new["moving"]
                flips, total = flips + flip, total + 1
                rss = {k: round(v, 5) for k, v in new.items() if k.startswith("rss")}
                print(f"{scene} {role} {i}: {n} frames, moving {old['moving']} -> {new['moving']} {rss}"
                      f"{'  FLIP' if flip else ''}", flush=True)
    print(f"{flips} of {total} recordings decided differently")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
