"""Modal decay evidence (matlearn.diagnosis.decay) over built diagnosis suite cases.

For every case folder (a scene.toml and the truth.json the suites write) it prints and records
the measured-over-nominal decay ratio of the train recordings, its z, the change concluded and
the true effects, then the spread of the ratio over cases with and without a damping change in
the truth: the evidence behind decay.DECAY_BAND. No simulation runs (seconds per case).

    python bench/decay_scan.py --work bench/work/diagnosis_suite bench/work/diagnosis_suite_random_1 ...
    python bench/decay_scan.py --work /tmp/w_named /tmp/w_r1 ... --out bench/results/decay_scan.json
"""
from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import code_commit  # noqa: E402



def true_effects(case: Path):
    """The case's true effects from what the suites write (suite_row.json, truth.json)."""
    row = case / "suite_row.json"
    if row.exists():
        return list(json.loads(row.read_text())["true_effects"])
    t = json.loads((case / "truth.json").read_text())
    eff = t.get("effects")
    if eff is None:
        eff = (t.get("extra") or {}).get("spec", {}).get("effects")
    return list(eff) if eff is not None else None


def scan(folders):
    from matlearn.diagnosis import decay
    from matlearn.diagnosis.problem import Problem

    rows = []
    for folder in folders:
        for scene in sorted(Path(folder).glob("*/scene.toml")):
            case = scene.parent
            eff = true_effects(case)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ev = decay.evidence(Problem(scene))
            row = {"suite": Path(folder).name, "case": case.name, "true_effects": eff, "ratio": ev["ratio"],
                   "z": ev["z"], "change": ev["change"],
                   "per_recording": [None if r is None else {"ratio": r["ratio"], "w": r["w"]}
                                     for r in ev["recordings"]]}
            rows.append(row)
            ratio = "-" if ev["ratio"] is None else f"{ev['ratio']:.2f}"
            print(f"{row['suite']:>22s} {case.name[:44]:44s} {','.join(eff or ['?'])[:44]:44s} ratio {ratio:>5s} "
                  f"change {ev['change']}", flush=True)
    return rows


def summary(rows) -> dict:
    from matlearn.diagnosis.selection import DISSIPATIVE

    known = [r for r in rows if r["true_effects"] is not None and r["ratio"] is not None]
    damped = [r for r in known if set(DISSIPATIVE) & set(r["true_effects"])]
    plain = [r for r in known if not set(DISSIPATIVE) & set(r["true_effects"])]

    def span(rs):
        v = [r["ratio"] for r in rs]
        return [float(min(v)), float(max(v))] if v else None

    return {"cases": len(rows), "no_usable_recording": sum(r["ratio"] is None for r in rows),
            "without_damping_change": {"cases": len(plain), "ratio_range": span(plain),
                                       "claimed": [r["case"] for r in plain if r["change"]]},
            "with_damping_change": {"cases": len(damped), "ratio_range": span(damped),
                                    "detected": sum(bool(r["change"]) for r in damped),
                                    "missed": [[r["case"], round(r["ratio"], 3)] for r in damped if not r["change"]]}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", nargs="+", required=True, help="suite work folders (one case per subfolder)")
    ap.add_argument("--out", type=Path, help="results JSON")
    args = ap.parse_args(argv)
    rows = scan(args.work)
    tot = summary(rows)
    print(json.dumps(tot, indent=1))
    if args.out:
        from matlearn.diagnosis import decay

        args.out.write_text(json.dumps({"commit": code_commit(), "band": list(decay.DECAY_BAND),
                                        "min_z": decay.MIN_Z, "totals": tot, "cases": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
