"""Choose score terms on a development set cheaply: collect each target's competing poses once,
then re-score them under every candidate score (issue 17's development protocol).

    python tools/score_study.py collect --dataset DEV --out POOL.npz [--scenes ..] [--max-images N]
        [--coarse-xy 0.03] [--coarse-yaw 15] [--pool 100] [--image-scale 0.5] [--clip 1.0] [--score thesis]
    python tools/score_study.py from-run RUN --out POOL.json [--pool 100]
    python tools/score_study.py merge POOL_A.json POOL_B.json ... --out POOL.json
    python tools/score_study.py rescore POOL.npz --score thesis --score surround=fill,shrink=16 ...
        [--alpha 0.5]
        [--out STUDY.json]
    python tools/score_study.py summary STUDY.json [--base SCORE]
    python tools/score_study.py values POOL.json --out VALUES/ [--score centred-direction] [--peaks 3]
    python tools/score_study.py reductions VALUES/ [--base top0.5] [--verbose]
    python tools/score_study.py values POOL.json --out VALUES_HALF/ --image-scale 0.5
    python tools/score_study.py blend VALUES/ VALUES_HALF/ [--weights 0.25 0.5] [--verbose]
    python tools/score_study.py values POOL.json --out VALUES_AROUND/ --around     # a from-run pool
    python tools/score_study.py occlusion VALUES_AROUND/ [--occluders run|truth] [--betas 0 0.25] [--verbose]

`collect` runs, per target (thesis protocol: height, roll and pitch from the ground truth), the
exact (pruned) search of the default region on a coarse grid under a score (`--score`, the thesis's
by default) and keeps its best `--pool` poses (the competitors), plus the ground truth's (x, y, yaw)
on the table. `merge` joins pools collected under several scores (interleaved by rank), so that a
variant is judged against the places it likes itself as well as those the baseline likes.
`from-run` takes the pool from a finished `perch_warp eval` run instead: each target's best
`--pool` cells of the grid its search scored (the heat map's `seen`: the best scored yaw per x, y),
so the competitors are those the run's own score and search found, at the run's resolution (the
run's answers, not the thesis's coarse grid).

`rescore` scores at full resolution, under each score, the pool, the ground truth's cell (within 1
cm and 5 deg of it at 5 mm / 2.5 deg, what a search would have to find) and the same cell around
each of the pool's best `--peaks` distinct poses away from the truth (so the distractors are refined
like the truth), takes the best of the union as a search would, and reports per score: ADD-S AUC,
ADD-S < 2 cm, how many targets the ground truth's cell wins (the score "explains" the photo best at
the truth), paired against the first score with a bootstrap interval of the difference. The ground
truth only defines the cell that is scored, never a score. It is an approximation of a full search
(the pool comes from one score's search: a place only another score ranks high is not in it), meant
for ranking variants; the frozen score is then checked with full searches (`perch_warp eval`).

`values` keeps, for the same poses as `rescore` (the pool, the far peaks' cells, the truth's cell), every
pose's feature-point values under one score below the grid (ScoringService.point_values: the numbers
whose top-α mean is its score) and its ADD-S, a file per target. `reductions` then tries other ways of
reducing a pose's values to its score (REDUCTIONS: top-α for several α, floors, an adaptive α, shrink)
on those files, without rendering anything again, and pairs each with the top-0.5 mean. `blend` pairs
one folder's top-0.5 means with their blend with another folder's, the same poses valued at another photo
scale (`values --image-scale 0.5`: conv1's 11 x 11 windows then see 22 x 22 pixels of the photo).
`occlusion` drops, from each pose's values, the points that lie under another target's answer in the
pool's run (its rendered silhouette, when its model origin is nearer the camera than the pose's) and
takes the top-0.5 mean of the rest, counted from at least beta of all points (hidden_top_mean); it
needs `values --pixels` (each point's photo pixel), and `--around` adds poses around and behind the
other answers, where such a score could newly favour a pose that hides behind them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from perch_warp import bop, pose_error
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.eval import journal
from perch_warp.eval.metrics import GeometryCache
from perch_warp.eval.plots import heatmap_path, silhouette
from perch_warp.features import load_feature_weights
from perch_warp.image import load_rgb
from perch_warp.mesh import load_mesh
from perch_warp.outputs import atomic_write, atomic_write_text
from perch_warp.score import alpha_count, hidden_count
from perch_warp.score_map import ScoreMap
from perch_warp.score_terms import DEFAULT_SCORE
from perch_warp.search_space import SearchSpace
from perch_warp.table import decompose_on_table, model_to_camera


def collect(args: argparse.Namespace) -> None:
    ds = bop.open_dataset(args.dataset, "test", args.models)
    sel = bop.select_targets(ds, args.scenes, args.objects, args.max_images)
    weights = load_feature_weights(args.weights)
    tables = bop.TableCache("auto")
    engines: dict[int, Engine] = {}
    cfg = EngineConfig(search="pruned", refine=False, top_k=args.pool, score=args.score, image_scale=args.image_scale)
    rows = []
    if args.out.is_file():  # resume: keep the targets already collected
        rows = json.loads(args.out.read_text())["targets"]
    have = {tuple(r["key"]) for r in rows}
    t_all = time.perf_counter()
    for im in sel.images:
        image = load_rgb(im.rgb)
        table, _ = tables.get(im)
        for tg in im.targets:
            if tuple(tg.key) in have:
                continue
            if tg.obj_id not in engines:
                engines[tg.obj_id] = Engine(load_mesh(sel.model_paths[tg.obj_id]), weights, "cpu", cfg)
            eng = engines[tg.obj_id]
            resting, gx, gy, gyaw = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
            space = SearchSpace.visible_table(
                im.camera, table, xy_step_m=args.coarse_xy, yaw_step_rad=math.radians(args.coarse_yaw), clip_m=args.clip
            )
            t = time.perf_counter()
            res = eng.estimate(image, im.camera, table, resting, space)
            pool = np.array([[c.x_m, c.y_m, c.yaw_rad] for c in res.top_k])
            rows.append(
                {
                    "key": [tg.scene_id, tg.im_id, tg.inst],
                    "obj_id": tg.obj_id,
                    "rgb": str(im.rgb),
                    "gt": [gx, gy, gyaw],
                    "pool": pool.tolist(),
                    "pool_scores": [c.score for c in res.top_k],
                }
            )
            print(
                f"{tg.scene_id}/{tg.im_id}/{tg.inst} obj {tg.obj_id}: {len(space)} candidates, "
                f"{res.info.evaluated} scored, {time.perf_counter() - t:.1f} s",
                file=sys.stderr,
                flush=True,
            )
            _save(args.out, args, rows)
    print(f"collected {len(rows)} targets in {time.perf_counter() - t_all:.0f} s -> {args.out}", file=sys.stderr)


def from_run(args: argparse.Namespace) -> None:
    run = Path(args.run)
    for f in (run / journal.CONFIG_FILE, run / journal.JOURNAL_FILE):
        if not f.is_file():
            raise PerchError(f"{f}: not found (from-run reads a perch_warp eval output folder)")
    cfg = json.loads((run / journal.CONFIG_FILE).read_text())
    ds = bop.open_dataset(cfg["dataset"], cfg.get("split", "test"), None)
    sel = bop.select_targets(ds)
    done, _, _ = journal.load_state(run, sel)  # eval's own reader: finished targets only, not failures
    by_key = {tuple(t.key): (im, t) for im in sel.images for t in im.targets}
    tables = bop.TableCache(cfg.get("table_source", "auto"))
    rows = []
    for key in sorted(done):
        im, tg = by_key[key]
        path = heatmap_path(run, key)
        if not path.is_file():
            raise PerchError(f"{path}: not found (the run's heat map of target {key}; was it run with this code?)")
        smap = ScoreMap.load(path)
        if smap.seen is None:
            raise PerchError(f"{path}: written before heat maps kept 'seen' (commit f0d8655); rerun the eval")
        table, _ = tables.get(im)
        _, gx, gy, gyaw = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
        i, j = np.nonzero(np.isfinite(smap.seen))
        order = np.lexsort((j, i, -smap.seen[i, j]))[: args.pool]
        i, j = i[order], j[order]
        pool = np.stack([smap.xs_m[i], smap.ys_m[j], smap.seen_yaw_rad[i, j]], -1)
        rows.append(
            {
                "key": list(key),
                "obj_id": tg.obj_id,
                "rgb": str(im.rgb),
                "gt": [gx, gy, gyaw],
                "pool": pool.tolist(),
                "pool_scores": smap.seen[i, j].tolist(),
            }
        )
    options = cfg.get("options") or {}
    meta = {"dataset": str(Path(cfg["dataset"]).resolve()), "models": None, "weights": options.get("weights", "auto"),
            "run": str(run.resolve()), "run_options": options, "targets": rows}  # fmt: skip
    atomic_write_text(args.out, json.dumps(meta))
    print(f"{len(rows)} targets' pools from {run} -> {args.out}", file=sys.stderr)


def _save(path: Path, args: argparse.Namespace, rows: list[dict]) -> None:
    meta = {
        "dataset": str(Path(args.dataset).resolve()),
        "models": str(args.models) if args.models else None,
        "weights": args.weights,
        "coarse_xy": args.coarse_xy,
        "coarse_yaw": args.coarse_yaw,
        "clip": args.clip,
        "image_scale": args.image_scale,
        "score": args.score,
        "targets": rows,
    }
    atomic_write_text(path, json.dumps(meta))


def _cell(pose) -> np.ndarray:
    """(125, 3) poses within 1 cm and 5 deg of a pose, at 5 mm / 2.5 deg: what a search on the default
    1 cm / 5 deg grid whose best peaks are refined would see there."""
    dxy = np.linspace(-0.01, 0.01, 5)
    dyaw = np.radians(np.linspace(-5.0, 5.0, 5))
    X, Y, A = np.meshgrid(pose[0] + dxy, pose[1] + dxy, pose[2] + dyaw, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), A.ravel()], -1)


GRID_XY_M, GRID_YAW_RAD = 0.01, math.radians(5.0)  # the default grid; the default region's origin is on it


def _grid_neighbours(pose) -> np.ndarray:
    """(8, 3) the default grid's poses around a pose: floor and ceiling in x, y and yaw."""
    axes = [
        np.floor(v / s) * s + np.array([0.0, s])
        for v, s in zip(pose, (GRID_XY_M, GRID_XY_M, GRID_YAW_RAD), strict=True)
    ]
    X, Y, A = np.meshgrid(*axes, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), A.ravel()], -1)


def _on_grid(poses: np.ndarray) -> np.ndarray:
    """Which poses lie on the default grid (multiples of 1 cm and 5 deg)."""
    q = poses / np.array([GRID_XY_M, GRID_XY_M, GRID_YAW_RAD])
    return np.all(np.abs(q - np.round(q)) < 1e-6, axis=1)


def merge(args: argparse.Namespace) -> None:
    """One pool from several (each `collect`ed under its own score) over the targets they share: each
    target's poses interleaved by rank (the first's best, the second's best, then the second best of
    each ...), repeats dropped, so every score's best places are among the first and `rescore`
    refines each score's peaks like the truth."""
    for p in args.pools:
        if not Path(p).is_file():
            raise PerchError(f"{p}: not found (merge reads pools written by collect or from-run)")
    metas = [json.loads(Path(p).read_text()) for p in args.pools]
    if len({m["dataset"] for m in metas}) != 1:
        raise PerchError("merge: the pools come from different datasets: " + ", ".join(str(p) for p in args.pools))
    by_key = [{tuple(r["key"]): r for r in m["targets"]} for m in metas]
    keys = [k for k in by_key[0] if all(k in b for b in by_key[1:])]
    per_pool = ("pool", "pool_scores", "thesis_scores")  # each source's own; thesis_scores: collect before stop 48
    rows = []
    for key in keys:
        pools = [np.asarray(b[key]["pool"], dtype=np.float64).reshape(-1, 3) for b in by_key]
        seen: set[tuple] = set()
        merged = []
        for i in range(max(len(q) for q in pools)):
            for q in pools:
                if i >= len(q):
                    continue
                pose = tuple(np.round(q[i], 6))
                if pose not in seen:
                    seen.add(pose)
                    merged.append(q[i].tolist())
        rows.append({**{k: v for k, v in by_key[0][key].items() if k not in per_pool}, "pool": merged})
    meta = {k: v for k, v in metas[0].items() if k != "targets"}
    meta["merged"] = [str(p) for p in args.pools]
    # collect's pools name their score, from-run's carry it in the run's options; older ones are the thesis's
    meta["score"] = [m.get("score") or (m.get("run_options") or {}).get("score") or "thesis" for m in metas]
    meta["targets"] = rows
    atomic_write_text(args.out, json.dumps(meta))
    print(f"{len(rows)} targets' pools merged from {len(metas)} -> {args.out}", file=sys.stderr)


def far_peaks(pool: np.ndarray, gt, n: int, apart_m: float = 0.03, away_m: float = 0.02) -> np.ndarray:
    """The best n pool poses (pool is best first) farther than away_m from the truth and apart_m from
    each other (greedy non-maximum suppression in x, y): the distractors that get a cell like the truth's."""
    keep: list[np.ndarray] = []
    for p in pool:
        if np.hypot(p[0] - gt[0], p[1] - gt[1]) <= away_m:
            continue
        if all(np.hypot(p[0] - q[0], p[1] - q[1]) > apart_m for q in keep):
            keep.append(p)
        if len(keep) == n:
            break
    return np.array(keep).reshape(-1, 3)


def _open_pool(pool: Path, weights: str | None, limit: int | None):
    """A pool file's dataset selection, its targets by key ((image, target)), its first `limit` rows that
    the dataset holds, and the feature weights (`weights`, else the pool's own)."""
    if not Path(pool).is_file():
        raise PerchError(f"{pool}: not found (rescore and values read pools written by collect, from-run or merge)")
    meta = json.loads(Path(pool).read_text())
    ds = bop.open_dataset(meta["dataset"], "test", meta["models"])
    sel = bop.select_targets(ds, sorted({t["key"][0] for t in meta["targets"]}))
    by_key = {tuple(t.key): (im, t) for im in sel.images for t in im.targets}
    rows = [t for t in meta["targets"] if tuple(t["key"]) in by_key][:limit]
    return sel, by_key, rows, load_feature_weights(weights or meta["weights"])


def _study_poses(row: dict, peaks: int) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """A pooled target's poses to score: its pool, the cell of each of its `peaks` best far peaks (so the
    distractors are refined like the truth, and neither side gains from the finer cell), the truth's cell."""
    pool = np.asarray(row["pool"], dtype=np.float64).reshape(-1, 3)
    return pool, [_cell(p) for p in far_peaks(pool, row["gt"], peaks)], _cell(row["gt"])


def rescore(args: argparse.Namespace) -> None:
    sel, by_key, targets, weights = _open_pool(args.pool, None, args.limit)
    tables = bop.TableCache("auto")
    results: dict[str, list[dict]] = {}
    meshes: dict[int, object] = {}
    points: dict[int, np.ndarray] = {}
    for spec in args.score:
        engines: dict[int, Engine] = {}
        out = []
        t0 = time.perf_counter()
        for row in targets:
            im, tg = by_key[tuple(row["key"])]
            if tg.obj_id not in meshes:
                meshes[tg.obj_id] = load_mesh(sel.model_paths[tg.obj_id])
                points[tg.obj_id] = pose_error.subsample_points(np.asarray(meshes[tg.obj_id].vertices_m))
            if tg.obj_id not in engines:
                engines[tg.obj_id] = _engines(meshes[tg.obj_id], weights, spec, args.alpha)
            out.append(_rescore_target(*engines[tg.obj_id], im, tg, row, tables, points[tg.obj_id], args))
        results[spec] = out
        _print_score_line(spec, out, t0)
    report = summarise(results, args.score[0])
    print(report["text"])
    if args.out:
        args.out.write_text(json.dumps({"pool": str(args.pool), "results": results, "summary": report}, indent=1))


def _engines(mesh, weights, spec: str, alpha: float) -> tuple[Engine, Engine]:
    """(grid engine, refining engine) of a score at top-alpha fraction `alpha`: the same, except that the
    refinement below the grid scores without the grid's shift tolerance (perch_warp.score_terms `shift`),
    as a search does."""
    cfg = EngineConfig(search="pruned", refine=False, score=spec, alpha=alpha)
    grid = Engine(mesh, weights, "cpu", cfg)
    if grid.terms.shift == 0:
        return grid, grid
    plain = grid.terms.below_grid().spec()
    return grid, Engine(mesh, weights, "cpu", dataclasses.replace(cfg, score=plain))


def _rescore_target(
    eng: Engine, fine_eng: Engine, im, tg, row: dict, tables, points: np.ndarray, args: argparse.Namespace
) -> dict:
    """One pooled target rescored by `eng` on the grid and `fine_eng` below it (_engines): the ADD-S (m) of
    the pose its score picks with every peak refined and with only the grid's best refined, and the best
    scores of the truth's cell, its grid neighbours and the pool (printed with --verbose)."""
    table, _ = tables.get(im)
    resting, *_ = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
    pool, peaks, cell = _study_poses(row, args.peaks)
    others = np.concatenate([pool, *peaks])
    grid_truth = _grid_neighbours(row["gt"])
    poses = np.concatenate([others, cell, grid_truth])
    image = load_rgb(im.rgb)
    fine = fine_eng.score(image, im.camera, table, resting, *poses.T)
    sc = fine
    n_o, n_c = len(others), len(cell)
    if eng is not fine_eng:  # the grid's poses (pool, the truth's grid neighbours) under the grid's score
        grid = np.flatnonzero(np.concatenate([_on_grid(others), np.zeros(n_c, bool), np.ones(len(grid_truth), bool)]))
        sc = fine.copy()
        sc[grid] = eng.score(image, im.camera, table, resting, *poses[grid].T)

    def adds(i: int) -> float:
        R, t = model_to_camera(table, resting, *poses[i : i + 1].T)
        return pose_error.adi(R[0], t[0], tg.R_gt, tg.t_gt_m, points)

    # "fine": the best peaks are all refined (truth's cell and the distractors' cells compete).
    e = adds(int(np.argmax(fine[: n_o + n_c])))
    # "grid": only the grid's best is refined: the truth competes with its grid neighbours only, and
    # wins refined (its cell's best) when one of them beats every grid pose of the distractors.
    on_grid = np.flatnonzero(_on_grid(others))
    far = on_grid[np.argmax(sc[on_grid])]
    e_grid = adds(n_o + int(np.argmax(sc[n_o : n_o + n_c]))) if sc[n_o + n_c :].max() > sc[far] else adds(far)
    pool_best = float(sc[:n_o].max())
    cell_best = float(sc[n_o : n_o + n_c].max())
    grid_best = float(sc[n_o + n_c :].max())
    if args.verbose:
        print(
            f"  {row['key']} obj {tg.obj_id}: truth's cell {cell_best:.4f} (grid {grid_best:.4f}), "
            f"others {pool_best:.4f}, ADD-S {100 * e:.2f} cm (grid only: {100 * e_grid:.2f} cm)",
            file=sys.stderr,
        )
    return {
        "key": row["key"],
        "obj_id": tg.obj_id,
        "adds_m": e,
        "adds_grid_m": e_grid,
        "cell": cell_best,
        "grid": grid_best,
        "pool": pool_best,
    }


def values(args: argparse.Namespace) -> None:
    """Every pooled pose's feature-point values under one score, a file per target (resumable)."""
    sel, by_key, rows, weights = _open_pool(args.pool, args.weights, args.limit)
    tables = bop.TableCache("auto")
    run = json.loads(Path(args.pool).read_text()).get("run")
    if (args.pixels or args.around) and not run:
        raise PerchError(f"{args.pool}: no run recorded (--pixels and --around need a pool made by from-run)")
    answers = run_answers(Path(run), sel) if args.around else None
    args.out.mkdir(parents=True, exist_ok=True)
    engines: dict[int, tuple[Engine, np.ndarray]] = {}
    t_all = time.perf_counter()
    for row in rows:
        path = args.out / values_file(row["key"])
        if path.is_file():
            continue
        t = time.perf_counter()
        im, tg = by_key[tuple(row["key"])]
        if tg.obj_id not in engines:
            mesh = load_mesh(sel.model_paths[tg.obj_id])
            cfg = EngineConfig(
                search="pruned", refine=False, score=args.score, alpha=0.5, cpu_threads=1, image_scale=args.image_scale
            )
            points = pose_error.subsample_points(np.asarray(mesh.vertices_m))
            engines[tg.obj_id] = (Engine(mesh, weights, "cpu", cfg), points)
        around = _poses_around(answers, tables.get(im)[0], tg) if answers is not None else None
        data = values_target(*engines[tg.obj_id], im, tg, row, tables, args.peaks, args.pixels or args.around, around)
        if args.pixels or args.around:
            data["run"] = np.str_(str(run))
        atomic_write(path, lambda f, data=data: np.savez_compressed(f, **data))
        print(f"{row['key']} obj {tg.obj_id}: {len(data['adds_m'])} poses, {time.perf_counter() - t:.1f} s",
              file=sys.stderr, flush=True)  # fmt: skip
    print(f"{len(rows)} targets' values in {args.out} ({time.perf_counter() - t_all:.0f} s)", file=sys.stderr)


def values_file(key) -> str:
    return "values_" + "_".join(str(k) for k in key) + ".npz"


def values_target(
    engine: Engine, points: np.ndarray, im, tg, row: dict, tables, peaks: int, pixels: bool = False, around=None
) -> dict:
    """One target's poses (the pool, each far peak's cell and the truth's cell: `kind` 0, 1, 2, then
    `around`'s poses if given: kind 3), their ADD-S (m) and every pose's feature-point values under the
    engine's score below the grid (the refinement's: the grid's shift tolerance off), concatenated
    (`lens` per pose). With `pixels`, also each point's photo pixel (`uv`) and each pose's model origin's
    distance from the camera (`dist_m`), what `occlusion` needs to tell the points another object hides."""
    table, _ = tables.get(im)
    resting, *_ = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
    pool, cells, truth = _study_poses(row, peaks)
    extra = np.zeros((0, 3)) if around is None else np.asarray(around, dtype=np.float64).reshape(-1, 3)
    poses = np.concatenate([pool, *cells, truth, extra])
    kind = np.repeat([0, 1, 2, 3], [len(pool), sum(len(c) for c in cells), len(truth), len(extra)]).astype(np.int8)
    service = engine.scoring(load_rgb(im.rgb), im.camera, table, resting).refining()
    vals = service.point_values((poses[:, 0], poses[:, 1], poses[:, 2]), pixels=pixels)
    uv = [p[1] for p in vals] if pixels else None
    vals = [p[0] for p in vals] if pixels else vals
    R, t = model_to_camera(table, resting, *poses.T)
    adds = np.array([pose_error.adi(R[i], t[i], tg.R_gt, tg.t_gt_m, points) for i in range(len(poses))])
    data = {
        "key": np.asarray(row["key"]),
        "obj_id": np.int64(tg.obj_id),
        "visib_fract": np.float64(np.nan if tg.visib_fract is None else tg.visib_fract),
        "poses": poses,
        "kind": kind,
        "adds_m": adds,
        "lens": np.array([len(v) for v in vals], dtype=np.int64),
        "values": np.concatenate([np.zeros(0, np.float32), *vals]),
        "image_scale": np.float64(engine.config.image_scale),
    }
    if pixels:
        data["uv"] = np.concatenate([np.zeros((0, 2), np.int32), *uv]).astype(np.int16)
        data["dist_m"] = np.linalg.norm(t, axis=1)
    return data


def run_answers(run: Path, sel) -> dict[tuple[int, int], list[tuple[int, int, np.ndarray, np.ndarray]]]:
    """A finished eval run's answers by image (scene, im): (inst, obj_id, R_m2c, t_m2c_m) per target."""
    if not (Path(run) / journal.JOURNAL_FILE).is_file():
        raise PerchError(f"{run}: no {journal.JOURNAL_FILE} (the pool's run must be a perch_warp eval output folder)")
    done, _, _ = journal.load_state(Path(run), sel)
    out: dict[tuple[int, int], list] = {}
    for (scene, im, inst), d in sorted(done.items()):
        out.setdefault((scene, im), []).append((inst, d.obj_id, np.asarray(d.R).reshape(3, 3), np.asarray(d.t_m)))
    return out


AROUND_M = np.arange(-0.12, 0.1201, 0.03)  # 9 x 9 places 3 cm apart
AROUND_YAW = np.radians(np.arange(0.0, 360.0, 45.0))


def _poses_around(answers: dict, table, tg) -> np.ndarray:
    """Table-frame poses (x_m, y_m, yaw_rad) around each OTHER target's answer in the same image, only
    those whose model origin is farther from the camera than that answer's: where a score that drops the
    points the answer hides might newly favour a pose mostly hidden behind it."""
    resting, *_ = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
    dx, dy, yaw = (a.ravel() for a in np.meshgrid(AROUND_M, AROUND_M, AROUND_YAW, indexing="ij"))
    out = [np.zeros((0, 3))]
    for inst, _, R, t in answers.get((tg.scene_id, tg.im_id), []):
        if inst == tg.inst:
            continue
        _, x, y, _ = decompose_on_table(table, R, t)
        poses = np.stack([x + dx, y + dy, yaw], 1)
        _, tr = model_to_camera(table, resting, *poses.T)
        out.append(poses[np.linalg.norm(tr, axis=1) > np.linalg.norm(t)])
    return np.concatenate(out)


def _top(alpha: float):
    return lambda m, s: m[alpha_count(alpha, len(s)) - 1]


def _floor(tau: float):
    return lambda m, s: float(np.maximum(s, tau).mean())


def _adaptive(p: float):
    def f(m: np.ndarray, s: np.ndarray) -> float:
        k = np.unique([alpha_count(a, len(s)) for a in np.arange(0.2, 1.0 + 1e-9, 0.05)])
        return float(np.max(m[k - 1] * (k / len(s)) ** p))

    return f


def _shrunk(k0: int):
    def f(m: np.ndarray, s: np.ndarray) -> float:
        k = alpha_count(0.5, len(s))
        return float(m[k - 1] * k / (k + k0))

    return f


# Reductions of a pose's n feature-point values (s: sorted, largest first; m[k - 1]: the mean of the best
# k) to its score. `top0.5` is every score's (the top-α mean, α = 0.5); each is non-decreasing in every
# value, so a silhouette bound of the same reduction of the points' ceilings would stay admissible.
REDUCTIONS = {
    **{f"top{a}": _top(a) for a in (0.25, 0.35, 0.5, 0.7, 1.0)},
    # every point counts, one below tau as tau: an occluded point costs at most tau, whatever covers it
    **{f"floor{t}": _floor(t) for t in (0.0, 0.1, 0.2, 0.3)},
    # the best top-a mean over a in [0.2, 1] times a^p: a smaller visible share may win if it matches better
    **{f"adaptive{p}": _adaptive(p) for p in (0.1, 0.2, 0.3, 0.5)},
    # the top-0.5 sum over k + k0 (score term shrink)
    **{f"shrink{k}": _shrunk(k) for k in (16, 64)},
}


def reduce_values(values: np.ndarray, lens: np.ndarray, names) -> dict[str, np.ndarray]:
    """Per reduction, each pose's score (-inf where it has no value)."""
    off = np.concatenate([[0], np.cumsum(lens)])
    out = {n: np.full(len(lens), -np.inf) for n in names}
    for i in np.flatnonzero(lens):
        s = np.sort(values[off[i] : off[i + 1]].astype(np.float64))[::-1]
        m = np.cumsum(s) / np.arange(1, len(s) + 1)
        for n in names:
            out[n][i] = REDUCTIONS[n](m, s)
    return out


def _values_files(folder: Path) -> list[Path]:
    files = sorted(Path(folder).glob("values_*.npz"))
    if not files:
        raise PerchError(f"{folder}: no values_*.npz (score_study.py values writes them)")
    return files


def reductions(args: argparse.Namespace) -> None:
    """Each reduction's pick per target (the best of all its poses: every peak refined), paired with the base."""
    files = _values_files(args.dir)
    if args.base not in REDUCTIONS:
        raise PerchError(f"--base {args.base}: not a reduction ({', '.join(REDUCTIONS)})")
    names = [args.base, *(n for n in REDUCTIONS if n != args.base)]
    targets = []
    for f in files:
        z = np.load(f)
        targets.append((z, reduce_values(z["values"], z["lens"], names)))
    _report_picks(targets, names, "reduction", args.verbose)


def blend(args: argparse.Namespace) -> None:
    """Each weight w's pick per target under (1 - w) top-0.5(values of `dir`) + w top-0.5(values of `other`),
    the same poses valued at two photo scales (values --image-scale), paired with w = 0 (`dir` alone)."""
    files = _values_files(args.dir)
    weights = {f"w{w:g}": w for w in (0.0, *args.weights)}
    names = list(weights)
    targets = []
    for f in files:
        z, path = np.load(f), Path(args.other) / f.name
        if not path.is_file():
            raise PerchError(f"{path}: missing (both folders need the same targets)")
        o = np.load(path)
        if not np.array_equal(z["poses"], o["poses"]):
            raise PerchError(f"{path}: other poses than {f} (both folders need the same pool)")
        a = reduce_values(z["values"], z["lens"], ["top0.5"])["top0.5"]
        b = reduce_values(o["values"], o["lens"], ["top0.5"])["top0.5"]
        targets.append((z, {n: _blend(a, b, w) if w else a for n, w in weights.items()}))
    _report_picks(targets, names, "blend", args.verbose)


def _blend(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """(1 - w) a + w b; -inf where a pose has no points at either scale (0 x -inf would be nan at w = 1)."""
    out = np.full(len(a), -np.inf)
    ok = np.isfinite(a) & np.isfinite(b)
    out[ok] = (1 - w) * a[ok] + w * b[ok]
    return out


def hidden_top_mean(values: np.ndarray, hidden: np.ndarray, beta: float, alpha: float = 0.5) -> float:
    """A pose's score when the points another, nearer object covers are dropped (`hidden`, bool per point):
    the sum of its best k visible values over k, k = alpha_count(alpha, max(V, ceil(beta N))) for V
    visible of N points (-inf with none visible). beta > 0 keeps a pose that hides almost wholly behind
    another object from winning on a few points: with V < beta N each missing point counts as 0. It
    never falls when a visible value rises, so a silhouette bound built the same way would stay an
    upper bound."""
    vis = np.sort(np.asarray(values, dtype=np.float64)[~np.asarray(hidden, dtype=bool)])[::-1]
    if not len(vis):
        return -math.inf
    k = alpha_count(alpha, hidden_count(beta, len(vis), len(values)))  # the engine's count (kernels/reduce.py)
    return float(vis[:k].sum() / k)


def hidden_points(uv: np.ndarray, dist_m: float, occluders: list[tuple[np.ndarray, float]]) -> np.ndarray:
    """Which of a pose's points (photo pixels uv (n, 2): column, row) lie under the silhouette (H, W) of
    an occluder whose model origin is nearer the camera than the pose's (dist_m): the comparison of
    centres perch_warp/joint.py makes (objects standing on a table rarely interleave)."""
    out = np.zeros(len(uv), dtype=bool)
    u, v = uv[:, 0].astype(np.int64), uv[:, 1].astype(np.int64)
    for mask, d in occluders:
        if d >= dist_m:
            continue
        h, w = mask.shape
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        out[inside] |= mask[v[inside], u[inside]]
    return out


def occlusion(args: argparse.Namespace) -> None:
    """Each target's pick when the points hidden by the other targets' answers in the pool's run (or, with
    --occluders truth, by every other object at its true pose: an upper bound) are dropped, paired with
    the top-0.5 mean of all points."""
    if bool(args.draw) != bool(args.draw_keys):
        raise PerchError("--draw FILE and --draw-keys KEY ... go together")
    draw_keys = [_parse_key(k) for k in args.draw_keys]
    names = ["top0.5", *(f"hidden{b:g}" for b in args.betas)]
    sources: dict[str, _Occluders] = {}
    targets, drawn = [], {}
    for f in _values_files(args.dir):
        z = dict(np.load(f))
        if "uv" not in z:
            raise PerchError(f"{f}: no point pixels (write the values with `values --pixels`)")
        run = str(z["run"])
        if run not in sources:
            sources[run] = _Occluders.of_run(Path(run), args.occluders)
        key = tuple(int(k) for k in z["key"])
        im, occluders = sources[run].of_target(key)
        scores, hidden = _occlusion_scores(z, occluders, args.betas)
        targets.append((z, scores))
        if key in draw_keys:
            drawn[key] = (z, scores, hidden, im, occluders)
    _report_picks(targets, names, f"occl. ({args.occluders})", args.verbose)
    if args.draw:
        _draw_occlusion(args, draw_keys, drawn)


def _parse_key(text: str) -> tuple[int, int, int]:
    """A target named scene/image/instance, e.g. 1/12/0."""
    parts = text.split("/")
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        raise PerchError(f"--draw-keys {text!r}: name a target as scene/image/instance, e.g. 1/12/0")
    return tuple(int(p) for p in parts)  # type: ignore[return-value]


def _occlusion_scores(z: dict, occluders: list[tuple[np.ndarray, float]], betas) -> tuple[dict, list]:
    """One target's scores per pose (top0.5 and hidden<beta>) and each pose's hidden points (bool arrays),
    given the silhouettes (H, W) and camera distances (m) of what may hide it."""
    off = np.concatenate([[0], np.cumsum(z["lens"])])
    scores = reduce_values(z["values"], z["lens"], ["top0.5"])
    for b in betas:
        scores[f"hidden{b:g}"] = np.full(len(z["lens"]), -np.inf)
    hidden = []
    for i in range(len(z["lens"])):
        v, uv = z["values"][off[i] : off[i + 1]], z["uv"][off[i] : off[i + 1]]
        hid = hidden_points(uv, float(z["dist_m"][i]), occluders)
        hidden.append(hid)
        if not len(v):
            continue  # no points: -inf under every beta, as under the top-0.5 mean
        for b in betas:
            scores[f"hidden{b:g}"][i] = hidden_top_mean(v, hid, b)
    return scores, hidden


def _draw_occlusion(args: argparse.Namespace, keys: list[tuple[int, int, int]], drawn: dict) -> None:
    """A picture per `--draw-keys` target side by side (args.draw, JPEG): the photo around the two picks,
    the occluders' outlines in white, the top-0.5 mean's pick's points in magenta, the pick with hidden
    points dropped (the first --betas) in green where visible and grey where hidden."""
    from PIL import Image, ImageDraw

    beta = args.betas[0]
    tiles = []
    for key in keys:
        if key not in drawn:
            path = Path(args.dir) / values_file(key)
            raise PerchError(f"{path}: missing (--draw-keys names targets as scene/image/instance)")
        z, scores, hidden, im, occluders = drawn[key]
        off = np.concatenate([[0], np.cumsum(z["lens"])])
        a, b = int(np.argmax(scores["top0.5"])), int(np.argmax(scores[f"hidden{beta:g}"]))
        pic = Image.open(im.rgb).convert("RGB")
        draw = ImageDraw.Draw(pic)
        for mask, _ in occluders:
            edge = mask & ~(np.roll(mask, 1, 0) & np.roll(mask, -1, 0) & np.roll(mask, 1, 1) & np.roll(mask, -1, 1))
            for v, u in np.argwhere(edge):
                draw.point((int(u), int(v)), fill=(255, 255, 255))
        marks = [(uv, (255, 0, 255)) for uv in z["uv"][off[a] : off[a + 1]]]
        for uv, h in zip(z["uv"][off[b] : off[b + 1]], hidden[b], strict=True):
            marks.append((uv, (150, 150, 150) if h else (0, 230, 0)))
        for (u, v), colour in marks:
            draw.rectangle([int(u) - 1, int(v) - 1, int(u) + 1, int(v) + 1], fill=colour)
        pts = np.array([m[0] for m in marks], dtype=np.float64).reshape(-1, 2)
        lo, hi = pts.min(0) - 30, pts.max(0) + 30
        w = min(max(hi[0] - lo[0], (hi[1] - lo[1]) * 4 / 3, 240), pic.width, pic.height * 4 / 3)
        x0 = float(np.clip((lo[0] + hi[0] - w) / 2, 0, pic.width - w))
        y0 = float(np.clip((lo[1] + hi[1]) / 2 - w * 3 / 8, 0, pic.height - w * 3 / 4))
        tile = pic.crop((int(x0), int(y0), int(x0 + w), int(y0 + w * 3 / 4))).resize((400, 300))
        name = "/".join(str(k) for k in key)
        label = f"{name}: top-0.5 mean {100 * z['adds_m'][a]:.1f} cm, hidden ({beta:g}) {100 * z['adds_m'][b]:.1f} cm"
        td = ImageDraw.Draw(tile)
        td.rectangle([0, 0, 400, 14], fill=(0, 0, 0))
        td.text((4, 2), label, fill=(255, 255, 0))
        tiles.append(tile)
    sheet = Image.new("RGB", (400 * len(tiles), 300))
    for i, tile in enumerate(tiles):
        sheet.paste(tile, (400 * i, 0))
    atomic_write(Path(args.draw), lambda f: sheet.save(f, format="JPEG", quality=85))
    print(f"picture: {args.draw}")


class _Occluders:
    """What may hide a target of a run's dataset: by image (scene, im), (inst, obj_id, R_m2c, t_m2c_m) of
    the run's answers ("run") or of every instance at its true pose ("truth"); each one's silhouette in
    the photo rendered once and kept, since every other target of its image asks for it. (A plain class:
    a dataclass needs its module in sys.modules, which a tool loaded from its file is not.)"""

    def __init__(self, by_key: dict, placed: dict, geometry: GeometryCache):
        self.by_key, self.placed, self.geometry = by_key, placed, geometry
        self.masks: dict[tuple[int, int, int], tuple[np.ndarray, float]] = {}

    @classmethod
    def of_run(cls, run: Path, which: str) -> _Occluders:
        cfg_path = run / journal.CONFIG_FILE
        if not cfg_path.is_file():
            raise PerchError(f"{cfg_path}: not found (the values' run must be a perch_warp eval output folder)")
        cfg = json.loads(cfg_path.read_text())
        sel = bop.select_targets(bop.open_dataset(cfg["dataset"], cfg.get("split", "test"), None))
        by_key = {tuple(t.key): (im, t) for im in sel.images for t in im.targets}
        if which == "run":
            placed = run_answers(run, sel)
        else:
            placed = {}
            for im in sel.images:
                placed[(im.scene_id, im.im_id)] = [(t.inst, t.obj_id, t.R_gt, t.t_gt_m) for t in im.targets]
        return cls(by_key, placed, GeometryCache(sel.model_paths))

    def of_target(self, key: tuple[int, int, int]):
        """The target's image and the (silhouette (H, W), distance from the camera in m) of every other
        instance placed in it."""
        im, _ = self.by_key[key]
        out = []
        for inst, obj, R, t in self.placed.get(key[:2], []):
            if inst == key[2]:
                continue
            k = (*key[:2], inst)
            if k not in self.masks:
                V, F, _ = self.geometry.get(obj)
                self.masks[k] = (silhouette(im.camera, V, F, R, t), float(np.linalg.norm(t)))
            out.append(self.masks[k])
        return im, out


def _report_picks(targets: list[tuple], names: list[str], what: str, verbose: bool) -> None:
    """Per way of scoring (names[0] the base), the ADD-S of each target's best pose (z["poses"] scored as
    scores[name]), AUC and < 2 cm paired with the base, by visibility, and the median margin."""
    base = names[0]
    results: dict[str, list[dict]] = {n: [] for n in names}
    margins: dict[str, list[float]] = {n: [] for n in names}
    visib = []
    for z, scores in targets:
        adds, right = z["adds_m"], z["adds_m"] < 0.02
        visib.append(float(z["visib_fract"]))
        both = right.any() and (~right).any()  # a margin needs a right and a wrong pose
        for n in names:
            e = float(adds[int(np.argmax(scores[n]))])
            results[n].append({"key": z["key"].tolist(), "adds_m": e, "adds_grid_m": e})
            # the best right pose's score less the best wrong one's
            margins[n].append(float(scores[n][right].max() - scores[n][~right].max()) if both else float("nan"))
    report = summarise(results, base)
    low = np.array(visib) < 0.5
    print(f"{len(targets)} targets, {int(low.sum())} less than half visible; every pose of each scored (all peaks "
          "refined), paired with " + base)  # fmt: skip
    print(f"{what:14s} {'AUC':>6s} {'dAUC [95% CI]':>22s} {'<2cm %':>7s} {'<2cm: vis<0.5':>13s} {'vis>=0.5':>9s}"
          f" {'median margin':>13s}  gained / lost against the base")  # fmt: skip
    e0 = np.array([o["adds_m"] for o in results[base]])
    for n in names:
        row, e = report["table"][n], np.array([o["adds_m"] for o in results[n]])
        keys = [tuple(o["key"]) for o in results[n]]
        gained = [keys[i] for i in np.flatnonzero((e < 0.02) & (e0 >= 0.02))]
        lost = [keys[i] for i in np.flatnonzero((e >= 0.02) & (e0 < 0.02))]
        lo_hit, hi_hit = int((e[low] < 0.02).sum()), int((e[~low] < 0.02).sum())
        print(f"{n:14s} {row['auc']:6.2f} {row['d_auc']:+7.2f} [{row['d_auc_ci'][0]:+6.2f},{row['d_auc_ci'][1]:+6.2f}]"
              f" {row['below_2cm']:7.2f} {lo_hit:>6d} of {int(low.sum()):<4d} {hi_hit:>3d} of {int((~low).sum()):<3d}"
              f" {np.nanmedian(margins[n]):+13.3f}  +{gained} -{lost}")  # fmt: skip
    if verbose:
        for i in range(len(targets)):
            cells = " ".join(f"{n} {100 * results[n][i]['adds_m']:.1f} cm ({margins[n][i]:+.3f})" for n in names)
            print(f"  {tuple(results[base][i]['key'])} visible {visib[i]:.2f}: {cells}")


def _print_score_line(spec: str, out: list[dict], t0: float) -> None:
    """One score's line on stderr: AUC and < 2 cm with every peak refined and with the grid's best only."""
    e = np.array([o["adds_m"] for o in out])
    g = np.array([o["adds_grid_m"] for o in out])
    print(
        f"{spec:40s} n {len(e)}  AUC {pose_error.auc(e):6.2f}  <2cm {100 * np.mean(e < 0.02):6.2f} %  "
        f"grid only: AUC {pose_error.auc(g):6.2f}  <2cm {100 * np.mean(g < 0.02):6.2f} %  "
        f"({time.perf_counter() - t0:.0f} s)",
        file=sys.stderr,
        flush=True,
    )


def _paired(x: np.ndarray, x0: np.ndarray, idx: np.ndarray) -> tuple[float, list[float]]:
    """Mean of x - x0 over the targets and its 95 % paired bootstrap interval (resamples idx)."""
    if not len(x):
        return 0.0, [0.0, 0.0]
    d = (x - x0)[idx].mean(1)
    return float((x - x0).mean()), [float(np.percentile(d, 2.5)), float(np.percentile(d, 97.5))]


def _metrics(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per target: the ADD-S AUC's term (100 max(0, 1 - e / 10 cm)) and 100 x (e < 2 cm)."""
    return 100 * np.maximum(0, 1 - e / 0.1), 100.0 * (e < 0.02)


def summarise(results: dict[str, list[dict]], base: str, n_boot: int = 2000, seed: int = 0) -> dict:
    """Per score: AUC and < 2 cm with every peak refined and with the grid's best only, each with the
    paired bootstrap interval (95 %, the same resamples of the targets) of the difference to `base`."""
    rng = np.random.default_rng(seed)
    n = len(results[base])
    idx = rng.integers(0, n, (n_boot, n)) if n else np.zeros((0, 0), int)
    ref = {k: _metrics(np.array([o[k] for o in results[base]])) for k in ("adds_m", "adds_grid_m")}
    lines = [
        f"{'score':40s} {'n':>3s} {'AUC':>7s} {'dAUC [95% CI]':>22s} {'<2cm %':>7s} {'d<2cm [95% CI]':>22s}"
        f" {'grid-only AUC':>13s} {'dAUC [95% CI]':>22s} {'<2cm':>6s} {'d<2cm [95% CI]':>22s}"
    ]
    table = {}
    for spec, out in results.items():
        row: dict = {"n": int(n)}
        for key, name in (("adds_m", ""), ("adds_grid_m", "grid_only_")):
            (a, w), (a0, w0) = _metrics(np.array([o[key] for o in out])), ref[key]
            row[f"{name}auc"] = float(a.mean()) if n else float("nan")
            row[f"{name}below_2cm"] = float(w.mean()) if n else float("nan")
            row[f"d_{name}auc"], row[f"d_{name}auc_ci"] = _paired(a, a0, idx)
            row[f"d_{name}below_2cm"], row[f"d_{name}below_2cm_ci"] = _paired(w, w0, idx)
        table[spec] = row
        cells = [f"{spec:40s} {n:3d}"]
        for name, width in (("", 7), ("grid_only_", 13)):
            cells.append(
                f"{row[f'{name}auc']:{width}.2f} {row[f'd_{name}auc']:+7.2f} [{row[f'd_{name}auc_ci'][0]:+6.2f},"
                f"{row[f'd_{name}auc_ci'][1]:+6.2f}] {row[f'{name}below_2cm']:{6 if name else 7}.2f} "
                f"{row[f'd_{name}below_2cm']:+7.2f} [{row[f'd_{name}below_2cm_ci'][0]:+6.2f},"
                f"{row[f'd_{name}below_2cm_ci'][1]:+6.2f}]"
            )
        lines.append(" ".join(cells))
    return {"base": base, "table": table, "text": "\n".join(lines)}


def show(args: argparse.Namespace) -> None:
    """The summary of a study written by `rescore --out`, again (against another base with --base)."""
    study = json.loads(Path(args.study).read_text())
    results = study["results"]
    base = args.base or next(iter(results))
    if base not in results:
        raise PerchError(f"{args.study}: no score {base!r} in the study (it has {', '.join(results)})")
    print(summarise(results, base)["text"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tools/score_study.py", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect", help="each target's competing poses under a score (the thesis's by default)")
    c.add_argument("--dataset", required=True)
    c.add_argument("--models", default=None)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--scenes", type=int, nargs="*")
    c.add_argument("--objects", type=int, nargs="*")
    c.add_argument("--max-images", type=int)
    c.add_argument("--weights", default="auto")
    c.add_argument("--coarse-xy", type=float, default=0.03, help="grid step, metres (default 0.03)")
    c.add_argument("--coarse-yaw", type=float, default=15.0, help="grid step, degrees (default 15)")
    c.add_argument("--clip", type=float, default=1.0, help="default region's square, metres (default 1)")
    c.add_argument("--pool", type=int, default=100, help="best poses kept per target (default 100)")
    c.add_argument("--score", default="thesis", help="the score whose best poses are kept (default thesis)")
    c.add_argument("--image-scale", type=float, default=0.5, help="photo scale of the collecting search (default 0.5)")
    f = sub.add_parser("from-run", help="each target's competing poses from a finished eval run's heat maps")
    f.add_argument("run", type=Path, help="the eval's output folder (targets.jsonl, heatmaps/)")
    f.add_argument("--out", type=Path, required=True)
    f.add_argument("--pool", type=int, default=100, help="best scored cells kept per target (default 100)")
    r = sub.add_parser("rescore", help="score the pools and the truth's cells under each score")
    r.add_argument("pool", type=Path)
    r.add_argument("--score", action="append", required=True, help="a score name or terms; repeat")
    r.add_argument("--limit", type=int)
    r.add_argument("--alpha", type=float, default=0.5, help="top-alpha fraction of every score (default 0.5)")
    r.add_argument("--peaks", type=int, default=3, help="distinct far pool peaks refined like the truth (default 3)")
    r.add_argument("--verbose", action="store_true", help="a line per target")
    r.add_argument("--out", type=Path)
    v = sub.add_parser("values", help="every pooled pose's feature-point values under one score, a file per target")
    v.add_argument("pool", type=Path)
    v.add_argument("--out", type=Path, required=True, help="folder of values_*.npz (resumes: files there are kept)")
    v.add_argument("--score", default=DEFAULT_SCORE, help=f"the score (default {DEFAULT_SCORE}); below the grid")
    v.add_argument("--weights", help="feature weights (default: the pool's run's)")
    v.add_argument("--peaks", type=int, default=3, help="distinct far pool peaks refined like the truth (default 3)")
    v.add_argument("--limit", type=int)
    v.add_argument("--image-scale", type=float, default=1.0, help="photo scale the poses are valued at (default 1)")
    v.add_argument("--pixels", action="store_true", help="keep each point's pixel and each pose's distance (occlusion)")
    v.add_argument(
        "--around",
        action="store_true",
        help="add poses around and behind the other targets' answers in the pool's run (implies --pixels)",
    )
    rd = sub.add_parser("reductions", help="each reduction of the stored values to a score, paired with the base")
    rd.add_argument("dir", type=Path, help="the folder `values` wrote")
    rd.add_argument("--base", default="top0.5", help="the reduction paired against (default top0.5, every score's)")
    rd.add_argument("--verbose", action="store_true", help="a line per target")
    b = sub.add_parser("blend", help="two folders of values (two photo scales) blended, paired with the first alone")
    b.add_argument("dir", type=Path, help="the folder `values` wrote (the base: weight 0)")
    b.add_argument("other", type=Path, help="the same pool's values at another scale (values --image-scale)")
    b.add_argument(
        "--weights", type=float, nargs="+", default=[0.25, 0.5], help="weights of `other` (default 0.25, 0.5)"
    )
    b.add_argument("--verbose", action="store_true", help="a line per target")
    oc = sub.add_parser("occlusion", help="picks when points the other targets' answers hide are dropped")
    oc.add_argument("dir", type=Path, help="the folder `values --pixels` wrote")
    oc.add_argument(
        "--betas",
        type=float,
        nargs="+",
        default=[0.0, 0.25, 0.5, 1.0],
        help="floors of the counted share: k from max(visible, beta x all points) (default 0 0.25 0.5 1)",
    )
    oc.add_argument(
        "--occluders",
        choices=["run", "truth"],
        default="run",
        help="the other targets' answers in the pool's run (default), or every object's true pose",
    )
    oc.add_argument("--verbose", action="store_true", help="a line per target")
    oc.add_argument("--draw", type=Path, help="a JPEG of the --draw-keys targets' two picks (the first --betas)")
    oc.add_argument("--draw-keys", nargs="+", default=[], help="targets to draw, as scene/image/instance")
    m = sub.add_parser("merge", help="one pool from several collected under different scores")
    m.add_argument("pools", type=Path, nargs="+")
    m.add_argument("--out", type=Path, required=True)
    sh = sub.add_parser("summary", help="a study's summary again (rescore --out's file)")
    sh.add_argument("study", type=Path)
    sh.add_argument("--base", help="the score the others are paired against (default: the first)")
    args = p.parse_args(argv)
    try:
        commands = {"collect": collect, "from-run": from_run, "merge": merge, "rescore": rescore, "summary": show,
                    "values": values, "reductions": reductions, "blend": blend, "occlusion": occlusion}  # fmt: skip
        commands[args.cmd](args)
    except PerchError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
