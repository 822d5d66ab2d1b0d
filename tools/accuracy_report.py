"""The accuracy figures of `perch_warp eval` runs with 95 % bootstrap intervals, and paired differences.

    python tools/accuracy_report.py OUT [--against BASE_OUT] [--json FILE]

Reads each run's per_target.csv (so it also serves runs whose summary predates `pooled_ci95`) and
prints, over its targets: the exact ADD-S AUC (the mean of max(0, 1 - e / 10 cm)), ADD-S < 2 cm, the
exact ADD AUC and translation error < 1 cm, each with a 95 % percentile bootstrap interval (targets
resampled, seed 0: `perch_warp.eval.metrics.mean_interval`). A failed target (no pose) counts as wrong.
With --against, the two runs are paired on the targets both hold (scene, image, instance) and the
differences OUT - BASE_OUT are given with paired intervals, with the targets that cross 2 cm either way
(scene/image/instance) and an exact two-sided sign test on them.
Exit 1 on bad input.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

from perch_warp.eval.metrics import mean_interval, target_shares

FIGURES = {
    "auc": "ADD-S AUC",
    "adds_below_2cm_pct": "ADD-S < 2 cm (%)",
    "auc_add": "ADD AUC",
    "te_below_1cm_pct": "translation < 1 cm (%)",
}


def read(out_dir: Path) -> dict[tuple[int, int, int], dict]:
    """per_target.csv keyed by (scene, image, instance); errors in metres, inf where the target failed."""
    path = out_dir / "per_target.csv"
    if not path.is_file():
        raise SystemExit(f"accuracy_report: {path} not found (an eval output folder holds per_target.csv)")

    def metres(v: str) -> float:
        return float(v) / 1000.0 if v not in ("", "nan", "inf") else np.inf

    with path.open(newline="") as f:
        return {
            (int(r["scene_id"]), int(r["im_id"]), int(r["inst"])): {
                "obj_id": int(r["obj_id"]),
                "adds_m": metres(r["adds_mm"]),
                "add_m": metres(r["add_mm"]),
                "te_m": metres(r["te_mm"]),
            }
            for r in csv.DictReader(f)
        }


def shares(rows: list[dict]) -> dict[str, np.ndarray]:
    return target_shares([r["adds_m"] for r in rows], [r["add_m"] for r in rows], [r["te_m"] for r in rows])


def sign_test_p(gained: int, lost: int) -> float:
    """Exact two-sided sign test on the discordant targets (found by one run only): the chance, were
    either run equally likely to find each of them, of a split at least this uneven."""
    n = gained + lost
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(gained, lost) + 1)) / 2**n
    return min(1.0, 2.0 * tail)


def _ids(keys: list) -> str:
    """ " (1/6/2, 1/8/0)": scene/image/instance of each target, or "" for none."""
    return " (" + ", ".join("/".join(map(str, k)) for k in keys) + ")" if keys else ""


def report(run: dict, base: dict | None = None) -> dict:
    keys = sorted(run)
    own = shares([run[k] for k in keys])
    out: dict = {
        "n": len(keys),
        "figures": {k: {"value": float(v.mean()), "ci95": mean_interval(v)} for k, v in own.items()},
    }
    if base is not None:
        common = sorted(set(run) & set(base))
        a, b = shares([run[k] for k in common]), shares([base[k] for k in common])
        ok_a, ok_b = a["adds_below_2cm_pct"] > 0, b["adds_below_2cm_pct"] > 0
        out["paired"] = {
            "n": len(common),
            "figures": {k: {"diff": float((a[k] - b[k]).mean()), "ci95": mean_interval(a[k] - b[k])} for k in a},
            "now_below_2cm": [list(k) for k, x, y in zip(common, ok_a, ok_b, strict=True) if x and not y],
            "no_longer_below_2cm": [list(k) for k, x, y in zip(common, ok_a, ok_b, strict=True) if y and not x],
        }
        p = out["paired"]
        p["sign_test_p"] = sign_test_p(len(p["now_below_2cm"]), len(p["no_longer_below_2cm"]))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="eval output folder")
    ap.add_argument("--against", type=Path, help="eval output folder of the run to pair with (the baseline)")
    ap.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    try:
        run = read(args.run)
        base = read(args.against) if args.against else None
    except SystemExit as e:
        print(e, file=sys.stderr)
        return 1
    if not run:
        print(f"accuracy_report: {args.run / 'per_target.csv'} holds no targets", file=sys.stderr)
        return 1
    rep = report(run, base)
    print(f"{args.run}: {rep['n']} targets (95 % bootstrap intervals, targets resampled)")
    for k, name in FIGURES.items():
        f = rep["figures"][k]
        print(f"  {name:<24}{f['value']:8.2f}   [{f['ci95'][0]:.2f}, {f['ci95'][1]:.2f}]")
    if "paired" in rep:
        p = rep["paired"]
        print(f"paired with {args.against} on {p['n']} common targets (this run minus that one)")
        for k, name in FIGURES.items():
            f = p["figures"][k]
            print(f"  {name:<24}{f['diff']:+8.2f}   [{f['ci95'][0]:+.2f}, {f['ci95'][1]:+.2f}]")
        print(
            f"  below 2 cm here only: {len(p['now_below_2cm'])}{_ids(p['now_below_2cm'])}; "
            f"there only: {len(p['no_longer_below_2cm'])}{_ids(p['no_longer_below_2cm'])}; "
            f"exact sign test p = {p['sign_test_p']:.2f}"
        )
    if args.json:
        args.json.write_text(json.dumps(rep, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
