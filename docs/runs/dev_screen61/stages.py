"""Per target of a merged `eval --joint --occluders answers` run: ADD-S of F_dir's answer, the first
pass's joint answer, the second pass's own best (before its joint step) and the final answer; the
AUC and < 2 cm count of each; the targets whose stages differ.

Usage: PYTHONPATH=. python stages.py MERGED F_DIR/per_target.csv
"""

import csv
import json
import sys

import numpy as np

from perch_warp import bop, pose_error
from perch_warp.eval.metrics import GeometryCache


def adds_m(target, points_m, R_m2c, t_m2c_m) -> float:
    """ADD-S (metres) of one pose against the target's ground truth."""
    R = np.asarray(R_m2c, dtype=float).reshape(3, 3)
    return pose_error.add_s(R, np.asarray(t_m2c_m, dtype=float), target.R_gt, target.t_gt_m, points_m)


def main(run: str, fdir_csv: str) -> None:
    cfg = json.load(open(f"{run}/eval_config.json"))
    sel = bop.select_targets(bop.open_dataset(cfg["dataset"], cfg.get("split", "test"), None))
    by_key = {tuple(t.key): t for im in sel.images for t in im.targets}
    geometry = GeometryCache(sel.model_paths)
    fdir = {
        (int(r["scene_id"]), int(r["im_id"]), int(r["inst"])): float(r["adds_mm"]) / 1000
        for r in csv.DictReader(open(fdir_csv))
    }
    cols = {"F_dir": [], "first_joint": [], "second_own": [], "final": []}
    for line in open(f"{run}/targets.jsonl"):
        r = json.loads(line)
        t = by_key[(r["scene_id"], r["im_id"], r["inst"])]
        pts = geometry.get(t.obj_id)[2]
        final = adds_m(t, pts, r["R"], np.array(r["t_mm"]) / 1000)
        occ = r["details"].get("occluders")
        joint = r["details"].get("joint") or {}
        first = adds_m(t, pts, occ["first_R_m2c"], occ["first_t_m2c_m"]) if occ else final
        own = final
        if joint.get("own_R_m2c") is not None:
            own = adds_m(t, pts, joint["own_R_m2c"], joint["own_t_m2c_m"])
        vals = (fdir[tuple(t.key)], first, own, final)
        for k, v in zip(cols, vals, strict=True):
            cols[k].append(v)
        if len({v < 0.02 for v in vals}) > 1 or max(vals) - min(vals) > 0.005:
            stages = " ".join(f"{k} {v * 100:6.2f}" for k, v in zip(cols, vals, strict=True))
            print(tuple(t.key), "obj", t.obj_id, stages)
    for k, v in cols.items():
        below = round(pose_error.accuracy_below(v) * len(v) / 100)
        print(f"{k:12s} n {len(v)} AUC {pose_error.auc(v):.2f} <2cm {below}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
