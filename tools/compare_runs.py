"""Do two `perch_warp eval` runs find the same poses? (e.g. a fast search against the exhaustive one)

    python tools/compare_runs.py REFERENCE_OUT OTHER_OUT [--tol-m 0.001] [--tol-deg 0.1]

Reads each run's per_target.csv, pairs targets by (scene, image, instance), and prints how
many have the same pose (x, y within --tol-m, yaw within --tol-deg: both runs search the same
grid, so equal poses are equal to rounding), and for the others which run's pose scores
higher (the reference's higher: the other search missed the maximum), then each run's mean
time per target and, where recorded, the share of candidates it scored. Exit 1 on bad input.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path


def read(out_dir: Path) -> dict[tuple[str, str, str], dict]:
    path = out_dir / "per_target.csv"
    if not path.is_file():
        raise SystemExit(f"compare_runs: {path} not found (an eval output folder holds per_target.csv)")
    with path.open(newline="") as f:
        return {(r["scene_id"], r["im_id"], r["inst"]): r for r in csv.DictReader(f)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("reference", type=Path, help="eval output folder of the reference run (e.g. exhaustive)")
    ap.add_argument("other", type=Path, help="eval output folder of the run to check")
    ap.add_argument("--tol-m", type=float, default=0.001, help="x/y tolerance, m (default 0.001)")
    ap.add_argument("--tol-deg", type=float, default=0.1, help="yaw tolerance, degrees (default 0.1)")
    args = ap.parse_args(argv)
    try:
        a, b = read(args.reference), read(args.other)
    except SystemExit as e:
        print(e, file=sys.stderr)
        return 1
    keys = sorted(set(a) & set(b))
    if not keys:
        print("compare_runs: the two runs share no target", file=sys.stderr)
        return 1
    same, ref_higher, other_higher, diff = 0, 0, 0, []
    for k in keys:
        ra, rb = a[k], b[k]
        dyaw = (float(ra["yaw_est_deg"]) - float(rb["yaw_est_deg"]) + 180.0) % 360.0 - 180.0
        dxy = math.hypot(float(ra["x_est_m"]) - float(rb["x_est_m"]), float(ra["y_est_m"]) - float(rb["y_est_m"]))
        if dxy <= args.tol_m and abs(dyaw) <= args.tol_deg:
            same += 1
            continue
        sa, sb = float(ra["score"]), float(rb["score"])
        ref_higher += sa > sb
        other_higher += sb > sa
        diff.append(f"  scene {k[0]} image {k[1]} inst {k[2]} (obj {ra['obj_id']}): scores {sa:.5f} vs {sb:.5f}")
    only = len(set(a) ^ set(b))
    print(f"targets in both runs   {len(keys)}" + (f" ({only} in only one, ignored)" if only else ""))
    print(f"same pose              {same} / {len(keys)} ({100 * same / len(keys):.1f} %)")
    print(f"reference scores higher {ref_higher} (the other search missed the maximum)")
    print(f"other scores higher     {other_higher}")
    for name, run in (("reference", a), ("other", b)):
        rows = [run[k] for k in keys]
        line = f"{name:<10} mean {_mean(rows, 'time_s'):.2f} s per target"
        if all(r.get("n_evaluated") for r in rows):  # eval runs since the pruned search record it
            frac = [float(r["n_evaluated"]) / float(r["n_candidates"]) for r in rows]
            line += f", scored {100 * sum(frac) / len(frac):.1f} % of the candidates on average"
        print(line)
    print("\n".join(diff))
    return 0


def _mean(rows: list[dict], key: str) -> float:
    vals = [float(r[key]) for r in rows if r.get(key)]
    return sum(vals) / len(vals) if vals else float("nan")


if __name__ == "__main__":
    sys.exit(main())
