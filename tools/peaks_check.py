"""How many grid peaks must be refined? Real searches (default region, grid and refinement) on chosen
targets of a BOP dataset, each refining its best K distinct peaks; since the peaks are chosen greedily
best first, one run with K peaks also gives the answer of every smaller K.

    python tools/peaks_check.py --dataset DEV --target 1/5/1 --target 1/6/4 ... [--peaks 8]
        [--score thesis] [--out CHECK.json]

Thesis protocol (height, roll, pitch from the ground truth; x, y, yaw searched over the visible table
clipped to 1 m at 1 cm / 5 deg, pruned search, refinement at 2 mm / 1 deg). Prints, per target and K,
the ADD-S of the answer the search with K peaks gives. The ground truth is used for the errors only.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from perch_warp import bop, pose_error
from perch_warp.engine import Engine, EngineConfig
from perch_warp.features import load_feature_weights
from perch_warp.image import load_rgb
from perch_warp.mesh import load_mesh
from perch_warp.search_space import SearchSpace
from perch_warp.table import decompose_on_table, model_to_camera


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tools/peaks_check.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--target", action="append", required=True, help="scene/image/instance, e.g. 1/5/1; repeat")
    p.add_argument("--peaks", type=int, default=8)
    p.add_argument("--score", default="thesis")
    p.add_argument("--weights", default="auto")
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    keys = [tuple(int(v) for v in t.split("/")) for t in args.target]
    ds = bop.open_dataset(args.dataset)
    sel = bop.select_targets(ds, sorted({k[0] for k in keys}))
    tables = bop.TableCache("auto")
    weights = load_feature_weights(args.weights)
    cfg = EngineConfig(search="pruned", refine_peaks=args.peaks, score=args.score)
    engines: dict[int, Engine] = {}
    rows = []
    for im in sel.images:
        for tg in im.targets:
            if tg.key not in keys:
                continue
            mesh = load_mesh(sel.model_paths[tg.obj_id])
            eng = engines.setdefault(tg.obj_id, Engine(mesh, weights, "cpu", cfg))
            table, _ = tables.get(im)
            resting, *_ = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
            space = SearchSpace.visible_table(im.camera, table, 0.01, math.radians(5.0), 1.0)
            t = time.perf_counter()
            res = eng.estimate(load_rgb(im.rgb), im.camera, table, resting, space)
            pts = pose_error.subsample_points(mesh.vertices_m)
            peaks = res.info.extra["refine"]["peaks"]
            errors = []
            for k in range(1, len(peaks) + 1):
                best = max(peaks[:k], key=lambda q: q["score"])
                pose = (np.array([best[a]]) for a in ("x_m", "y_m", "yaw_rad"))
                R, tr = model_to_camera(table, resting, *pose)
                errors.append(pose_error.adi(R[0], tr[0], tg.R_gt, tg.t_gt_m, pts))
            rows.append(
                {
                    "key": list(tg.key),
                    "obj_id": tg.obj_id,
                    "adds_m_by_k": errors,
                    "peaks": peaks,
                    "scored": res.info.evaluated,
                    "candidates": res.n_candidates,
                    "seconds": time.perf_counter() - t,
                }
            )
            print(
                f"{tg.key} obj {tg.obj_id}: ADD-S cm by K = "
                + " ".join(f"{100 * e:.1f}" for e in errors)
                + f"  ({time.perf_counter() - t:.0f} s)",
                file=sys.stderr,
                flush=True,
            )
            if args.out:
                args.out.write_text(json.dumps({"dataset": args.dataset, "score": args.score, "targets": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
