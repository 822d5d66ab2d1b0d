"""First pass against second pass per target of an `eval --joint --occluders answers` journal (partial runs too).

    python docs/runs/dev_screen58/pairs.py OUT

Prints each target's ADD-S (the dataset's ground truth) of the first pass's joint answer (details.occluders)
and of the journalled (second-pass) answer, and the AUC and < 2 cm of both; a run's summary.json gives the
same pairing once the run is complete.
"""

import json
import sys

import numpy as np

from perch_warp import bop, pose_error
from perch_warp.eval.metrics import GeometryCache


def main(run: str) -> None:
    cfg = json.load(open(f"{run}/eval_config.json"))
    sel = bop.select_targets(bop.open_dataset(cfg["dataset"], cfg.get("split", "test"), None))
    by_key = {tuple(t.key): t for im in sel.images for t in im.targets}
    geometry = GeometryCache(sel.model_paths)
    first, second = [], []
    for line in open(f"{run}/targets.jsonl"):
        r = json.loads(line)
        t = by_key[(r["scene_id"], r["im_id"], r["inst"])]
        pts = geometry.get(t.obj_id)[2]
        e2 = pose_error.add_s(np.array(r["R"]).reshape(3, 3), np.array(r["t_mm"]) / 1000, t.R_gt, t.t_gt_m, pts)
        o = r["details"].get("occluders")  # absent for an image with one target: no second pass
        e1 = e2
        if o is not None:
            e1 = pose_error.add_s(np.array(o["first_R_m2c"]), np.array(o["first_t_m2c_m"]), t.R_gt, t.t_gt_m, pts)
        first.append(e1)
        second.append(e2)
        flag = "" if (e1 < 0.02) == (e2 < 0.02) else ("GAINED" if e2 < 0.02 else "LOST")
        print(f"{tuple(t.key)} obj {t.obj_id}: first {e1 * 100:6.2f} cm  second {e2 * 100:6.2f} cm  {flag}")
    for name, e in (("first", np.array(first)), ("second", np.array(second))):
        auc = 100 * np.mean(np.maximum(0, 1 - e / 0.1))
        print(f"{name}: n {len(e)}, ADD-S AUC {auc:.2f}, < 2 cm {100 * np.mean(e < 0.02):.1f} %")


if __name__ == "__main__":
    main(sys.argv[1])
