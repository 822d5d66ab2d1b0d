"""Per target of the merged run: ADD-S of F_dir's answer, the first pass's joint answer, the second pass's
own best (before its joint step) and the final answer; AUC and < 2 cm of each; the targets that differ."""
import csv, json, sys
import numpy as np
from perch_warp import bop, pose_error
from perch_warp.eval.metrics import GeometryCache

run = sys.argv[1]
cfg = json.load(open(f"{run}/eval_config.json"))
sel = bop.select_targets(bop.open_dataset(cfg["dataset"], cfg.get("split", "test"), None))
by_key = {tuple(t.key): t for im in sel.images for t in im.targets}
geometry = GeometryCache(sel.model_paths)
fdir = {(int(r["scene_id"]), int(r["im_id"]), int(r["inst"])): float(r["adds_mm"]) / 1000
        for r in csv.DictReader(open(sys.argv[2]))}
cols = {"F_dir": [], "first_joint": [], "second_own": [], "final": []}
for line in open(f"{run}/targets.jsonl"):
    r = json.loads(line)
    t = by_key[(r["scene_id"], r["im_id"], r["inst"])]
    pts = geometry.get(t.obj_id)[2]
    e = lambda R, tt: pose_error.add_s(np.asarray(R).reshape(3, 3), np.asarray(tt), t.R_gt, t.t_gt_m, pts)
    fin = e(r["R"], np.array(r["t_mm"]) / 1000)
    o = r["details"].get("occluders")
    j = r["details"].get("joint") or {}
    first = e(o["first_R_m2c"], o["first_t_m2c_m"]) if o else fin
    own = e(j["own_R_m2c"], j["own_t_m2c_m"]) if j.get("own_R_m2c") is not None else fin
    vals = (fdir[tuple(t.key)], first, own, fin)
    for k, v in zip(cols, vals):
        cols[k].append(v)
    if len({v < 0.02 for v in vals}) > 1 or max(vals) - min(vals) > 0.005:
        print(tuple(t.key), "obj", t.obj_id, " ".join(f"{k} {v*100:6.2f}" for k, v in zip(cols, vals)))
for k, v in cols.items():
    v = np.array(v)
    print(f"{k:12s} n {len(v)} AUC {100*np.mean(np.maximum(0,1-v/0.1)):.2f} <2cm {int((v<0.02).sum())}")
