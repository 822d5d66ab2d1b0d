"""Did an `eval` run's search lose the grid's maximum near the ground truth? (its misses only)

    python tools/grid_check.py OUT [--min-adds-mm 20] [--device cpu]

For each target of the finished run in OUT whose ADD-S is at least --min-adds-mm: the grid stage's
score (the run's own score, e.g. grid-tolerant) of the grid nodes that enclose the ground truth's
(x, y, yaw) in the table frame (one step or less away on each axis: 8 nodes unless the truth sits on
a node), against the grid score from which the run refined its answer (`refine.from.score` in the
journal). If a truth node scores higher, the search did not return the grid's maximum (coarse-to-fine
can miss it; the exact searches cannot), so the exact search would have answered otherwise. If none
does, the exact search's grid maximum is not beside the truth either and the target is lost by it too.

The run's settings are rebuilt from its own command line (summary.json's `command`), so the grid and
the score are the run's; only --device may differ. The ground truth is read here, after the search,
as `eval`'s diagnostics do. Runs under `--rest truth` only, without `--joint`. Exit 1 on bad input.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shlex
import sys
from pathlib import Path

import numpy as np


def run_args(out_dir: Path, device: str | None) -> argparse.Namespace:
    """The run's `eval` options, parsed from the command line its summary.json records."""
    from perch_warp.eval.command import add_arguments

    summary = out_dir / "summary.json"
    if not summary.is_file():
        raise SystemExit(f"grid_check: {summary} not found (a finished eval output folder holds summary.json)")
    words = shlex.split(json.loads(summary.read_text())["command"])
    if words[:4] != ["python", "-m", "perch_warp", "eval"]:
        raise SystemExit(f"grid_check: {summary}'s command is not a `python -m perch_warp eval` line: {words[:4]}")
    parser = argparse.ArgumentParser(prog="eval")
    add_arguments(parser)
    args = parser.parse_args(words[4:])
    if args.rest != "truth":
        raise SystemExit(f"grid_check: the run searched --rest {args.rest}; only --rest truth runs are checked")
    if args.joint:
        # Its answers come from the joint step's choice among each target's peaks and, with the second pass,
        # from scores with points hidden by the other answers: one target's plain grid maximum says nothing of them.
        raise SystemExit(
            "grid_check: the run searched with --joint; only runs that search each target alone are checked "
            "(compare a --joint run with the exact search instead: the same command with --search pruned)"
        )
    if device is not None:
        args.device = device
    return args


def truth_nodes(space, x_m: float, y_m: float, yaw_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grid nodes within one step of the truth on every axis (yaw on the circle)."""
    xs, ys, yaws = space.axes()
    step_yaw = space.yaw_step_rad
    near_x = xs[np.abs(xs - x_m) < space.xy_step_m + 1e-9]
    near_y = ys[np.abs(ys - y_m) < space.xy_step_m + 1e-9]
    turn = np.abs((yaws - yaw_rad + math.pi) % (2 * math.pi) - math.pi)
    near_yaw = yaws[turn < step_yaw + 1e-9]
    gx, gy, gyaw = np.meshgrid(near_x, near_y, near_yaw, indexing="ij")
    return gx.ravel(), gy.ravel(), gyaw.ravel()


def check(out_dir: Path, min_adds_mm: float, device: str | None) -> list[dict]:
    from perch_warp import bop
    from perch_warp.bop.targets import TableCache, select_targets
    from perch_warp.eval.command import _ids
    from perch_warp.eval.journal import load_state
    from perch_warp.eval.protocol import EngineEstimator, prepare_job
    from perch_warp.image import load_rgb
    from perch_warp.options import engine_config_from_args, search_space_from_args

    args = run_args(out_dir, device)
    for name in ("per_target.csv", "targets.jsonl"):
        if not (out_dir / name).is_file():
            raise SystemExit(f"grid_check: {out_dir / name} not found (the run's folder is incomplete)")
    with (out_dir / "per_target.csv").open(newline="") as f:
        missed = {
            (int(r["scene_id"]), int(r["im_id"]), int(r["inst"])): r
            for r in csv.DictReader(f)
            if r["adds_mm"] and float(r["adds_mm"]) >= min_adds_mm
        }
    ds = bop.open_dataset(args.dataset, args.split, args.models)
    sel = select_targets(
        ds, _ids(args.scenes, "--scenes"), _ids(args.objects, "--objects"), args.max_images, args.table_source
    )
    done, _, _ = load_state(out_dir, sel)  # eval's own reader of the journal (a damaged line is skipped, said)
    tables = TableCache(args.table_source)
    estimator = EngineEstimator(sel.model_paths, args.weights, args.device, engine_config_from_args(args))

    def space_fn(camera, table, resting):
        return search_space_from_args(args, camera, table)

    rows = []
    for im in sel.images:
        image = None
        for t in im.targets:
            key = (t.scene_id, t.im_id, t.inst)
            if key not in missed:
                continue
            refine = done[key].details.get("refine") if key in done else None
            if not refine:
                raise SystemExit(f"grid_check: target {key} has no refinement record in {out_dir / 'targets.jsonl'}")
            job = prepare_job(im, t, tables, space_fn)
            # The truth's place as eval's diagnostics take it (the "truth's cell" they score).
            xg, yg, yawg = EngineEstimator.probe(t, job.table, job.resting)["probe"]
            x, y, yaw = truth_nodes(job.space, xg, yg, yawg)
            image = load_rgb(im.rgb) if image is None else image
            scores = estimator.engine(t.obj_id).score(image, job.camera, job.table, job.resting, x, y, yaw)
            best = int(np.argmax(scores))
            row = {
                "scene_id": t.scene_id,
                "im_id": t.im_id,
                "inst": t.inst,
                "obj_id": t.obj_id,
                "adds_mm": float(missed[key]["adds_mm"]),
                "miss": missed[key].get("miss"),
                "truth_nodes": len(x),
                "truth_node_best": float(scores[best]),
                "truth_node_x_m": float(x[best]),
                "truth_node_y_m": float(y[best]),
                "truth_node_yaw_deg": math.degrees(float(yaw[best])),
                "answer_grid_score": float(refine["from"]["score"]),
            }
            row["lost_grid_max"] = row["truth_node_best"] > row["answer_grid_score"]
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path, help="a finished `eval --rest truth` output folder")
    ap.add_argument("--min-adds-mm", type=float, default=20.0, help="check targets with ADD-S at least this (20)")
    ap.add_argument("--device", help="Warp device for the scoring (default: the run's)")
    args = ap.parse_args(argv)
    from perch_warp.errors import PerchError

    try:
        rows = check(args.out, args.min_adds_mm, args.device)
    except SystemExit as e:
        print(e, file=sys.stderr)
        return 1
    except PerchError as e:  # e.g. the run's dataset is no longer where its command line says
        print(f"grid_check: {e}", file=sys.stderr)
        return 1
    lost = [r for r in rows if r["lost_grid_max"]]
    print(
        f"{len(rows)} targets with ADD-S >= {args.min_adds_mm:g} mm; on {len(lost)} the search lost the grid's "
        "maximum (a grid node beside the truth scores higher than the node the answer was refined from)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
