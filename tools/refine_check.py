"""Does the refinement find the best fine pose near the grid's best? For every target of an eval run,
an exhaustive search at the refinement's resolution over a window wider than its cell, against the refined pose.

    python tools/refine_check.py EVAL_OUT [--cells 2] [--limit N] [--out CHECK.json]

EVAL_OUT is a `perch_warp eval` folder made with refinement on (its targets.jsonl records each
target's refined pose and score and the grid pose it started from) on a BOP dataset whose
images are found again from its eval_config.json. The refinement searches the best grid pose's
cell, one grid step either side, at (by default) 2 mm / 1°; here the window is --cells grid
steps either side, at the same fine steps, with the eval's method options (the pruned search:
the same best as the exhaustive one). "As good" when the refined score is at least the
window's best (less 1e-6): the fine optimum did not lie in a neighbouring cell. "Same pose"
when the two poses are within one fine step. Exit 1 on bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from perch_warp.bench import load_workload
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.features import load_feature_weights
from perch_warp.refine import cell_space
from perch_warp.search_space import FULL_CIRCLE, SearchSpace

SCORE_TOL = 1e-6  # float32 cosines: equal scores can differ in the last places


def _yaw_diff_deg(a_rad: float, b_rad: float) -> float:
    return abs(math.degrees((a_rad - b_rad + math.pi) % (2 * math.pi) - math.pi))


def check(eval_out: Path, cells: int, device: str, limit: int | None = None, log=print) -> dict:
    cfg, targets, jl_path = _read_eval(eval_out, limit)
    opt = cfg["options"]
    config = EngineConfig(
        stride=opt["stride"],
        alpha=opt["alpha"],
        clusters=opt["clusters"],
        seed=opt["seed"],
        relu=opt["relu"],
        image_scale=opt["image_scale"],
        cpu_threads=opt.get("cpu_threads"),
        search="pruned",
        refine=False,
        top_k=1,
    )
    weights = load_feature_weights(opt["weights"])
    grid_xy, grid_yaw = opt["xy_step"], math.radians(opt["yaw_step"])
    engines: dict[int, Engine] = {}
    rows = []
    for n, t in enumerate(targets, 1):
        if t["details"].get("refine") is None:
            raise PerchError(f"{jl_path}: scene {t['scene_id']} image {t['im_id']} has no refinement details")
        w = load_workload(
            cfg["dataset"], t["scene_id"], t["im_id"], t["obj_id"], opt["clip"], grid_xy, grid_yaw, cfg["split"]
        )
        if t["obj_id"] not in engines:
            engines[t["obj_id"]] = Engine(w.mesh, weights, device, config)
        row = _check_target(engines[t["obj_id"]], w, t, opt, cells)
        rows.append(row)
        log(
            f"[{n}/{len(targets)}] scene {t['scene_id']} image {t['im_id']} obj {t['obj_id']}: refined "
            f"{row['refined']['score']:.5f}, window best {row['window_best']['score']:.5f} over "
            f"{row['candidates']} poses ({row['dxy_m'] * 1000:.1f} mm, {row['dyaw_deg']:.1f} deg apart), "
            f"{row['seconds']:.1f} s"
        )
    n = len(rows)
    return {
        "eval_out": str(eval_out),
        "device": device,
        "cells": cells,
        "targets": n,
        "as_good": sum(r["as_good"] for r in rows),
        "same_pose": sum(r["same_pose"] for r in rows),
        "refine_evaluated_mean": float(np.mean([r["refine_evaluated"] for r in rows])) if rows else None,
        "cell_candidates_mean": float(np.mean([r["candidates"] for r in rows])) if rows else None,
        "rows": rows,
    }


def _read_eval(eval_out: Path, limit: int | None) -> tuple[dict, list[dict], Path]:
    """A `perch_warp eval` folder made with refinement: its eval_config.json, its first `limit` journalled
    targets and the journal's path."""
    cfg_path, jl_path = eval_out / "eval_config.json", eval_out / "targets.jsonl"
    for p in (cfg_path, jl_path):
        if not p.is_file():
            raise PerchError(f"{p} not found: give a `perch_warp eval` output folder")
    cfg = json.loads(cfg_path.read_text())
    if not cfg["options"].get("refine", False):
        raise PerchError(f"{eval_out} was made without refinement (its options have no refine: true)")
    targets = [json.loads(line) for line in jl_path.read_text().splitlines() if line.strip()][:limit]
    return cfg, targets, jl_path


def _check_target(engine: Engine, w, t: dict, opt: dict, cells: int) -> dict:
    """One journalled target: the best of the window of `cells` grid steps around the pose its refinement
    started from (searched whole, pruned), against the refined pose the run reported."""
    ref = t["details"]["refine"]
    grid_xy, grid_yaw = opt["xy_step"], math.radians(opt["yaw_step"])
    x0, y0, yaw0 = ref["from"]["x_m"], ref["from"]["y_m"], math.radians(ref["from"]["yaw_deg"])
    (rx0, rx1), (ry0, ry1) = t["details"]["region_m"]
    grid = SearchSpace((rx0, rx1), (ry0, ry1), grid_xy, FULL_CIRCLE, grid_yaw)
    space = cell_space(grid, x0, y0, yaw0, opt["refine_xy"], math.radians(opt["refine_yaw"]), cells)
    step_xy_m, step_yaw_deg = space.xy_step_m, math.degrees(space.yaw_step_rad)
    t0 = time.perf_counter()
    best = engine.estimate(w.image, w.camera, w.table, w.resting, space).best
    refined = t["details"]["top_k"][0]
    dxy = math.hypot(refined["x_m"] - best.x_m, refined["y_m"] - best.y_m)
    dyaw = _yaw_diff_deg(refined["yaw_rad"], best.yaw_rad)
    return {
        "scene_id": t["scene_id"],
        "im_id": t["im_id"],
        "obj_id": t["obj_id"],
        "candidates": len(space),
        "step_xy_m": step_xy_m,
        "step_yaw_deg": step_yaw_deg,
        "refined": refined,
        "refine_evaluated": ref["evaluated"],
        "window_best": {"x_m": best.x_m, "y_m": best.y_m, "yaw_rad": best.yaw_rad, "score": best.score},
        "as_good": refined["score"] >= best.score - SCORE_TOL,
        "same_pose": dxy <= step_xy_m * (1 + 1e-6) and dyaw <= step_yaw_deg * (1 + 1e-6),
        "dxy_m": dxy,
        "dyaw_deg": dyaw,
        "seconds": time.perf_counter() - t0,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("eval_out", type=Path, help="a `perch_warp eval` output folder made with refinement on")
    ap.add_argument("--cells", type=int, default=2, help="window: grid steps either side of the grid pose (2)")
    ap.add_argument("--limit", type=int, default=None, help="only the first N targets of the run")
    ap.add_argument("--device", default="cpu", help="Warp device (default: cpu)")
    ap.add_argument("--out", type=Path, default=None, help="write the per-target figures here as JSON")
    args = ap.parse_args(argv)
    try:
        if args.cells < 1 or (args.limit is not None and args.limit < 1):
            raise PerchError(f"--cells and --limit must be at least 1, got {args.cells} and {args.limit}")
        r = check(args.eval_out, args.cells, args.device, args.limit)
    except PerchError as e:
        print(f"refine_check: {e}", file=sys.stderr)
        return 1
    n = r["targets"]
    print(
        f"refined score >= the best of a search at its resolution over {args.cells} grid steps either side: "
        f"{r['as_good']} / {n}; pose within one fine step of it: {r['same_pose']} / {n} "
        f"(refinement scored {r['refine_evaluated_mean']:.0f} poses, the window {r['cell_candidates_mean']:.0f})"
    )
    if args.out:
        args.out.write_text(json.dumps(r, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
