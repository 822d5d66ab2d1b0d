"""What `eval ... --refine-peaks K [--refine-yaws M]` answers, from a K = 1 run's own grid, without its search.

    python tools/peaks_replay.py RUN --out OUT [--refine-peaks 4] [--refine-yaws 1] [--device cpu]

Under coarse-to-fine (and exhaustive) the grid search does not depend on --refine-peaks or
--refine-yaws: they act after it (perch_warp/engine.py `Engine._search`: the best candidate of each
of the best `pool` locations, then search.refine.refine_peaks). So the run's grid is reused and only
the refinements are computed, seconds per target instead of the minutes a search takes on a CPU.
The pruned search's grid does depend on them (it keeps the K-th location exact): such runs are
refused, as are runs under --rest stable or --joint.

Per finished target of RUN (its journal, eval's own reader), with the run's settings rebuilt from its
eval_config.json (only --refine-peaks, --refine-yaws and --device replaced):
1. The run's heat map (heatmaps/, ScoreMap `seen`: each location's best scored candidate and its
   yaw) gives the best candidate of every scored location. The heat map keeps scores as float32, so
   every location whose float32 score reaches the `pool`-th best (rounding is monotonic: the true
   best `pool` are among them) is scored again, in float64, by the run's own scoring service
   (`Engine.scoring`, the renderer the search used). Each rescored value must round to the stored
   one; then they are ordered as `Engine._search` orders them (peaks.top_location_candidates).
2. Check: refining the best location alone must give the run's journal answer bit for bit (its
   refinement's grid pose and score and its refined score). A target that fails the check stops the
   tool with exit 1 and its reason; nothing half-written is left.
3. search.refine.refine_peaks with the new K and M gives the answer.

Writes OUT/per_target.csv (eval's columns, through eval's own error computation, so that
tools/accuracy_report.py pairs it with RUN) and OUT/replay.jsonl (per target: the K = 1 check, the
peaks refined, the answer); it resumes from replay.jsonl. The ground truth is read for the errors
only, after the answer (and for the diagnostics' truth cell, copied from RUN's journal). An answer
that differs from RUN's gets no silhouette or confidence diagnostics (those columns are left empty).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

REPLAY_FILE = "replay.jsonl"


def run_args(run: Path, device: str | None, peaks: int, yaws: int) -> argparse.Namespace:
    """RUN's `eval` options from its eval_config.json, with --refine-peaks/--refine-yaws (and --device) replaced."""
    from perch_warp.eval.command import add_arguments
    from perch_warp.eval.journal import CONFIG_FILE

    path = run / CONFIG_FILE
    if not path.is_file():
        raise SystemExit(f"peaks_replay: {path} not found (RUN must be a `perch_warp eval` output folder)")
    cfg = json.loads(path.read_text())
    parser = argparse.ArgumentParser(prog="eval")
    add_arguments(parser)
    args = parser.parse_args(["--dataset", str(cfg["dataset"]), "--out", str(run)])
    for k, v in (cfg.get("options") or {}).items():
        if not hasattr(args, k):
            raise SystemExit(f"peaks_replay: {path}: option {k!r} is unknown to this eval (a run of other code?)")
        setattr(args, k, tuple(v) if isinstance(v, list) and k.endswith("_range") else v)
    args.split = cfg.get("split", args.split)
    args.table_source = cfg.get("table_source", args.table_source)
    if args.search not in ("coarse-to-fine", "exhaustive"):
        raise SystemExit(
            f"peaks_replay: {run} searched --search {args.search}; only coarse-to-fine and exhaustive grids do not "
            "depend on --refine-peaks"
        )
    if args.rest != "truth" or args.joint:
        raise SystemExit(f"peaks_replay: {run} searched --rest stable or --joint; only single --rest truth runs replay")
    if not args.refine:
        raise SystemExit(f"peaks_replay: {run} ran without refinement (--no-refine): there is nothing to replay")
    if args.refine_peaks != 1 or args.refine_yaws != 1:
        raise SystemExit(
            f"peaks_replay: {run} already refined {args.refine_peaks} peaks and {args.refine_yaws} yaws; "
            "replay a K = 1, M = 1 run"
        )
    if peaks < 1 or yaws < 1:
        raise SystemExit(f"peaks_replay: --refine-peaks and --refine-yaws must be at least 1, got {peaks} and {yaws}")
    args.refine_peaks, args.refine_yaws = peaks, yaws
    if device is not None:
        args.device = device
    return args


def pool_locations(smap, pool: int, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(i, j, seen) of the heat map's locations whose float32 best seen score is at least the `pool`-th best's:
    the true best `pool` locations are among them whatever the float64 scores were."""
    seen32 = np.asarray(smap.seen, dtype=np.float32)
    ok = np.isfinite(seen32)
    if not ok.any():
        raise SystemExit(f"peaks_replay: {name}: the heat map holds no scored location")
    i, j = np.nonzero(ok)
    s = seen32[i, j]
    cut = np.sort(s)[::-1][min(pool, len(s)) - 1]
    keep = s >= cut
    return i[keep], j[keep], s[keep]


def grid_candidates(smap, space, pool: int, name: str):
    """(flat, x_m, y_m, yaw_rad, seen32) of the pool's candidates on the search's grid, from the heat map."""
    xs, ys, yaws = space.axes()
    if (
        len(xs) != len(smap.xs_m)
        or len(ys) != len(smap.ys_m)
        or not (np.allclose(xs, smap.xs_m, atol=1e-9) and np.allclose(ys, smap.ys_m, atol=1e-9))
    ):
        raise SystemExit(f"peaks_replay: {name}: the heat map's grid is not the run's search grid (other settings?)")
    i, j, s = pool_locations(smap, pool, name)
    yaw_seen = np.asarray(smap.seen_yaw_rad, dtype=np.float64)[i, j]
    turn = np.abs((yaws[None, :] - yaw_seen[:, None] + math.pi) % (2 * math.pi) - math.pi)
    k = np.argmin(turn, axis=1)
    if (turn[np.arange(len(k)), k] > 1e-5).any():
        raise SystemExit(f"peaks_replay: {name}: a heat map's yaw is not one of the search grid's yaws")
    flat = (i * len(ys) + j) * len(yaws) + k
    order = np.argsort(flat)  # ascending flat, as every search returns it
    return flat[order], xs[i][order], ys[j][order], yaws[k][order], s[order]


def replay_target(engine, image, job, smap, done, config, name: str) -> dict:
    """One target: the K = 1 check against the run's journal (done: its Done), then refine_peaks; `name`:
    the heat map's file, for errors."""
    from perch_warp.peaks import top_location_candidates
    from perch_warp.search.refine import refine, refine_peaks

    space = job.space
    service = engine.scoring(image, job.camera, job.table, job.resting, space)
    flat, x, y, yaw, seen32 = grid_candidates(smap, space, config.pool, name)
    scores = service.quiet().score((x, y, yaw))
    if not np.array_equal(scores.astype(np.float32), seen32):
        bad = int(np.argmax(scores.astype(np.float32) != seen32))
        raise SystemExit(
            f"peaks_replay: target {job.target.key}: the grid pose x {x[bad]:+.3f} y {y[bad]:+.3f} yaw "
            f"{math.degrees(yaw[bad]):.1f} scores {scores[bad]!r} now, {float(seen32[bad])!r} in the run's heat map"
        )
    order = top_location_candidates(flat, scores, len(space.axes()[2]), config.pool)
    top = [(float(x[n]), float(y[n]), float(yaw[n]), float(scores[n])) for n in order]

    origin = (done.details.get("refine") or {}).get("from")
    if not origin:
        raise SystemExit(f"peaks_replay: target {job.target.key} has no refinement record in the run's journal")
    made = refine(service, space, [top[0]], engine.search)
    first = made[0][0]  # the best location refined: (x_m, y_m, yaw_rad, score)

    def refine_fn(svc, space_, poses: list, grid_search: str):  # the best peak's refinement made once
        return made if poses[0][:3] == top[0][:3] else refine(svc, space_, poses, grid_search)

    check = {
        "grid": [top[0][0], top[0][1], math.degrees(top[0][2]), top[0][3]],
        "run_grid": [origin["x_m"], origin["y_m"], origin["yaw_deg"], origin["score"]],
        "refined_score": first[3],
        "run_score": done.score,
    }
    same_grid = (
        origin["score"] == top[0][3]
        and abs(origin["x_m"] - top[0][0]) < 1e-9
        and abs(origin["y_m"] - top[0][1]) < 1e-9
        and abs(origin["yaw_deg"] - math.degrees(top[0][2])) < 1e-6
    )
    if not (same_grid and first[3] == done.score):
        raise SystemExit(f"peaks_replay: target {job.target.key}: refining the best location alone does not give "
                         f"the run's answer: {json.dumps(check)}")  # fmt: skip
    best_top, info = refine_peaks(service, space, top, engine.search, refine_fn)
    answer = best_top[0]
    return {
        "key": list(job.target.key),
        "obj_id": job.target.obj_id,
        "check": check,
        "answer": {"x_m": answer[0], "y_m": answer[1], "yaw_rad": answer[2], "score": answer[3]},
        "same_as_run": answer[3] == done.score and answer[:3] == first[:3],
        "peaks": info.get("peaks", []),
    }


def read_journal(path: Path) -> list[dict]:
    """replay.jsonl's rows; a line cut short (a process killed while writing it) is skipped, said, and redone."""
    rows = []
    if not path.is_file():
        return rows
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            print(f"peaks_replay: {path} line {n} is cut short; its target is replayed again", file=sys.stderr)
    return rows


def shard_of(spec: str | None) -> tuple[int, int]:
    """--shard "I/N" as (I, N): this process takes the targets whose place in the run's order is I modulo N."""
    if spec is None:
        return 0, 1
    try:
        i, n = (int(v) for v in spec.split("/"))
    except ValueError:
        raise SystemExit(f"peaks_replay: --shard must be I/N, e.g. 0/2, got {spec!r}") from None
    if not (n >= 1 and 0 <= i < n):
        raise SystemExit(f"peaks_replay: --shard I/N needs 0 <= I < N, got {spec!r}")
    return i, n


def replay(
    run: Path, out: Path, peaks: int, yaws: int, device: str | None, limit: int | None = None, shard: str | None = None
) -> list[dict]:
    from perch_warp import bop
    from perch_warp.bop.targets import TableCache, select_targets
    from perch_warp.eval.command import _ids
    from perch_warp.eval.journal import load_state
    from perch_warp.eval.metrics import GeometryCache, compute_errors, write_per_target
    from perch_warp.eval.plots import heatmap_path
    from perch_warp.eval.protocol import EngineEstimator, prepare_job
    from perch_warp.image import load_rgb
    from perch_warp.options import engine_config_from_args, search_space_from_args
    from perch_warp.outputs import atomic_write_text
    from perch_warp.score_map import ScoreMap
    from perch_warp.table import model_to_camera

    args = run_args(run, device, peaks, yaws)
    ds = bop.open_dataset(args.dataset, args.split, args.models)
    sel = select_targets(ds, _ids(args.scenes, "--scenes"), _ids(args.objects, "--objects"), None, args.table_source)
    done, _, _ = load_state(run, sel)  # eval's own reader (finished targets only)
    if not done:
        raise SystemExit(f"peaks_replay: {run} holds no finished target")
    config = engine_config_from_args(args)
    estimator = EngineEstimator(sel.model_paths, args.weights, args.device, config)
    tables = TableCache(args.table_source)

    def space_fn(camera, table, resting):
        return search_space_from_args(args, camera, table)

    out.mkdir(parents=True, exist_ok=True)
    journal = out / REPLAY_FILE
    rows = read_journal(journal)
    have = {tuple(r["key"]) for r in rows}
    i_shard, n_shards = shard_of(shard)
    finished = [(im, t) for im in sel.images for t in im.targets if tuple(t.key) in done]
    todo = [p for n, p in enumerate(finished) if n % n_shards == i_shard and tuple(p[1].key) not in have]
    todo = todo[:limit] if limit is not None else todo
    for n, (im, t) in enumerate(todo, 1):
        t0 = time.perf_counter()
        path = heatmap_path(run, t.key)
        if not path.is_file():
            raise SystemExit(f"peaks_replay: {path} not found (the run's heat map of target {t.key})")
        smap = ScoreMap.load(path)
        if smap.seen is None:
            raise SystemExit(f"peaks_replay: {path} predates heat maps' 'seen' (commit f0d8655)")
        job = prepare_job(im, t, tables, space_fn)
        row = replay_target(
            estimator.engine(t.obj_id), load_rgb(im.rgb), job, smap, done[tuple(t.key)], config, str(path)
        )
        row["seconds"] = time.perf_counter() - t0
        # One write per line, appended: shards side by side on one journal never interleave within a line.
        fd = os.open(journal, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, (json.dumps(row) + "\n").encode())
        finally:
            os.close(fd)
        rows.append(row)
        what = "same answer" if row["same_as_run"] else f"new answer, score {row['answer']['score']:.4f}"
        print(f"[{n}/{len(todo)}] {'/'.join(map(str, t.key))} obj {t.obj_id}: {what} ({row['seconds']:.0f} s)",
              file=sys.stderr, flush=True)  # fmt: skip

    replayed = {}
    by_key = {tuple(r["key"]): r for r in rows}
    for im in sel.images:
        table, _ = tables.get(im)
        for t in im.targets:
            r = by_key.get(tuple(t.key))
            if r is None:
                continue
            base = done[tuple(t.key)]
            if r["same_as_run"]:
                replayed[tuple(t.key)] = base
                continue
            a = r["answer"]
            job = prepare_job(im, t, tables, space_fn)
            R, tr = model_to_camera(
                table, job.resting, np.array([a["x_m"]]), np.array([a["y_m"]]), np.array([a["yaw_rad"]])
            )
            details = {
                k: v for k, v in base.details.items() if k not in ("silhouette", "confidence", "top_k", "refine")
            }
            replayed[tuple(t.key)] = dataclasses.replace(base, R=R[0], t_m=tr[0], score=a["score"], details=details)
    errors = compute_errors(sel, replayed, tables, GeometryCache(sel.model_paths))
    write_per_target(out / "per_target.csv", errors)  # atomically
    meta = {"run": str(run.resolve()), "refine_peaks": peaks, "refine_yaws": yaws, "targets": len(rows)}
    atomic_write_text(out / "replay_config.json", json.dumps(meta, indent=1))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a `perch_warp eval` output folder (K = 1, coarse-to-fine or exhaustive)")
    ap.add_argument("--out", type=Path, required=True, help="folder for per_target.csv and replay.jsonl (resumed)")
    ap.add_argument("--refine-peaks", type=int, default=4, help="K, as eval's --refine-peaks (default 4)")
    ap.add_argument("--refine-yaws", type=int, default=1, help="M, as eval's --refine-yaws (default 1)")
    ap.add_argument("--device", help="Warp device (default: the run's)")
    ap.add_argument("--limit", type=int, metavar="N", help="replay at most N more targets (a check on a few)")
    ap.add_argument(
        "--shard",
        metavar="I/N",
        help="take every N-th target from the I-th (processes side by side on one --out, each its own shard; "
        "then one more call with --limit 0 writes per_target.csv over them all)",
    )
    args = ap.parse_args(argv)
    from perch_warp.errors import PerchError

    try:
        rows = replay(args.run, args.out, args.refine_peaks, args.refine_yaws, args.device, args.limit, args.shard)
    except SystemExit as e:
        print(e, file=sys.stderr)
        return 1
    except PerchError as e:
        print(f"peaks_replay: {e}", file=sys.stderr)
        return 1
    changed = sum(not r["same_as_run"] for r in rows)
    print(
        f"{len(rows)} targets replayed with K = {args.refine_peaks}, M = {args.refine_yaws}: {changed} answers "
        f"differ from the run's; {args.out / 'per_target.csv'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
