"""Which grid peaks must be refined? Real grid searches once, then every peak strategy from them.

    python tools/peaks_check.py collect --dataset DEV --out POOL.json [--target 1/5/1 ...]
        [--scenes 1] [--max-images N] [--score thesis]
    python tools/peaks_check.py refine POOL.json --out CHECK.json [--peaks 1 2 4 8] [--yaws 1 2 3]
        [--separation 3 5]

`collect` runs, per target (thesis protocol: height, roll and pitch from the ground truth), the real
grid search (visible table clipped to 1 m, 1 cm / 5 deg, pruned, exact) ranking table *locations* by
their best score over yaw, and stores its best 256 locations (each with its best grid yaw) and the
ground truth's table pose, resuming where a previous run stopped. `refine` rebuilds each photo's
scoring service and evaluates each strategy (K peaks at least S grid steps apart, M yaws per peak's
place, perch_warp.search.refine.refine_place itself), refining each grid pose once (cached
across strategies), and reports per strategy ADD-S < 2 cm and ADD-S AUC, paired with the first
strategy (bootstrap interval of the difference over targets). The ground truth is used for the
errors only. Since a strategy with (K, M, S) is what `--refine-peaks K --refine-yaws M` computes,
no search is repeated: one photo's grid costs minutes on the CPU, a refinement seconds.
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
from perch_warp.features import load_feature_weights
from perch_warp.image import load_rgb
from perch_warp.mesh import load_mesh
from perch_warp.peaks import distinct_peaks, top_location_candidates
from perch_warp.search import pruned
from perch_warp.search.refine import refine, refine_place
from perch_warp.search_space import SearchSpace
from perch_warp.table import decompose_on_table, model_to_camera

POOL_LOCATIONS = 256
YAW_STEP_DEG = 5.0


def _space(im, table) -> SearchSpace:
    return SearchSpace.visible_table(im.camera, table, 0.01, math.radians(YAW_STEP_DEG), 1.0)


def _targets(args: argparse.Namespace):
    """(image, target) pairs of the dataset chosen by --target or by --scenes/--max-images, in order."""
    ds = bop.open_dataset(args.dataset)
    keys = [tuple(int(v) for v in t.split("/")) for t in args.target or []]
    scenes = sorted({k[0] for k in keys}) if keys else args.scenes
    sel = bop.select_targets(ds, scenes, None, None if keys else args.max_images)
    pairs = [(im, tg) for im in sel.images for tg in im.targets if not keys or tuple(tg.key) in keys]
    return sel, pairs


def collect(args: argparse.Namespace) -> None:
    sel, pairs = _targets(args)
    tables, weights = bop.TableCache("auto"), load_feature_weights(args.weights)
    cfg = EngineConfig(search="pruned", refine_peaks=POOL_LOCATIONS // 32, score=args.score)
    rows = json.loads(args.out.read_text())["targets"] if args.out.is_file() else []
    have = {tuple(r["key"]) for r in rows}
    engines: dict[int, Engine] = {}
    for im, tg in pairs:
        if tuple(tg.key) in have:
            continue
        eng = engines.setdefault(tg.obj_id, Engine(load_mesh(sel.model_paths[tg.obj_id]), weights, "cpu", cfg))
        table, _ = tables.get(im)
        resting, gx, gy, gyaw = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
        space = _space(im, table)
        t = time.perf_counter()
        service = eng.scoring(load_rgb(im.rgb), im.camera, table, resting, space)
        out = pruned.run(service, space)
        flat = np.arange(len(out.scores))
        pos = top_location_candidates(flat, out.scores, len(space.axes()[2]), POOL_LOCATIONS)
        x, y, yaw = space.at(pos)
        pool = [[float(x[n]), float(y[n]), float(yaw[n]), float(out.scores[i])] for n, i in enumerate(pos)]
        rows.append(
            {
                "key": list(tg.key),
                "obj_id": tg.obj_id,
                "gt": [gx, gy, gyaw],
                "pool": pool,
                "scored": out.evaluated,
                "candidates": len(space),
                "seconds": time.perf_counter() - t,
            }
        )
        print(
            f"{tg.key} obj {tg.obj_id}: {len(space)} candidates, {out.evaluated} scored, "
            f"{time.perf_counter() - t:.0f} s",
            file=sys.stderr,
            flush=True,
        )
        _write(args.out, {"dataset": args.dataset, "score": args.score, "targets": rows})


def _write(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)


def strategies(args: argparse.Namespace) -> list[tuple[int, int, int]]:
    """(K peaks, M yaws, S separation steps), the first one (K = M = 1) the baseline."""
    out = [(1, 1, args.separation[0])]
    for s in args.separation:
        for k in args.peaks:
            for m in args.yaws:
                if (k, m, s) not in out and not (k == 1 and s != args.separation[0]):
                    out.append((k, m, s))
    return out


def refine_target(service, space, pool: list, plan: list[tuple[int, int, int]], grid_search: str = "pruned"):
    """Per strategy (K, M, S): the answer (x_m, y_m, yaw_rad, score), search.refine.refine_place at each of
    the K peaks with M yaws, the best of them; each grid pose refined once across strategies."""
    cache: dict[tuple, tuple] = {}

    def refine_once(svc, space, top: list, grid_search: str):
        key = tuple(round(v, 9) for v in top[0][:3])
        if key not in cache:
            cache[key] = refine(svc, space, top, grid_search)
        return cache[key]

    answers = {}
    for k, m, s in plan:
        cfg = dataclasses.replace(service.config, refine_yaws=m)
        svc = dataclasses.replace(service, config=cfg)
        peaks = distinct_peaks(pool, k, s * space.xy_step_m)
        places = [refine_place(svc, space, tuple(pool[i]), grid_search, refine_once)[0] for i in peaks]
        answers[(k, m, s)] = max(places, key=lambda c: c[3])  # the first of equal bests, as refine_place keeps
    return answers, len(cache)


def _name(strategy: tuple[int, int, int]) -> str:
    return "K{}/M{}/S{}".format(*strategy)


def refine_all(args: argparse.Namespace) -> None:
    data = json.loads(args.pool.read_text())
    args.dataset, args.target, args.scenes, args.max_images = data["dataset"], None, None, None
    keys = {tuple(r["key"]): r for r in data["targets"]}
    sel, pairs = _targets(args)
    tables, weights = bop.TableCache("auto"), load_feature_weights(args.weights)
    cfg = EngineConfig(search="pruned", score=data["score"])
    plan = strategies(args)
    done = json.loads(args.out.read_text())["targets"] if args.out and args.out.is_file() else []
    have = {tuple(r["key"]) for r in done}
    engines: dict[int, Engine] = {}
    for im, tg in pairs:
        row = keys.get(tuple(tg.key))
        if row is None or tuple(tg.key) in have:
            continue
        mesh = load_mesh(sel.model_paths[tg.obj_id])
        eng = engines.setdefault(tg.obj_id, Engine(mesh, weights, "cpu", cfg))
        table, _ = tables.get(im)
        resting, *_ = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
        space = _space(im, table)
        t = time.perf_counter()
        service = eng.scoring(load_rgb(im.rgb), im.camera, table, resting, space)
        answers, n_refined = refine_target(service, space, row["pool"], plan)
        pts = pose_error.subsample_points(mesh.vertices_m)
        errors = {}
        for strat, (x, y, yaw, score) in answers.items():
            R, tr = model_to_camera(table, resting, np.array([x]), np.array([y]), np.array([yaw]))
            errors[_name(strat)] = [pose_error.adi(R[0], tr[0], tg.R_gt, tg.t_gt_m, pts), score]
        done.append({"key": list(tg.key), "obj_id": tg.obj_id, "errors": errors, "refined": n_refined})
        base = errors[_name(plan[0])][0]
        best = min(errors.items(), key=lambda e: e[1][0])
        print(
            f"{tg.key} obj {tg.obj_id}: ADD-S {100 * base:.1f} cm at K=M=1, best {best[0]} "
            f"{100 * best[1][0]:.1f} cm; {n_refined} refinements, {time.perf_counter() - t:.0f} s",
            file=sys.stderr,
            flush=True,
        )
        if args.out:
            _write(args.out, {"pool": str(args.pool), "targets": done})
    print(json.dumps(summarise(done, [_name(p) for p in plan]), indent=1))


def summarise(rows: list[dict], names: list[str], n_boot: int = 2000, seed: int = 0) -> dict:
    """Per strategy: < 2 cm and ADD-S AUC (%), and their paired differences with names[0] with 95 % bootstrap
    intervals over targets."""
    e = np.array([[r["errors"][n][0] for n in names] for r in rows])
    below = 100.0 * (e < 0.02)
    auc = 100.0 * np.maximum(0.0, 1.0 - e / 0.10)
    rng = np.random.default_rng(seed)
    boot = rng.integers(0, len(rows), size=(n_boot, len(rows)))
    out = {"targets": len(rows)}
    for j, n in enumerate(names):
        d_below, d_auc = below[:, j] - below[:, 0], auc[:, j] - auc[:, 0]
        out[n] = {
            "below_2cm": float(below[:, j].mean()),
            "auc": float(auc[:, j].mean()),
            "d_below_2cm": [float(d_below.mean()), *np.percentile(d_below[boot].mean(1), [2.5, 97.5]).tolist()],
            "d_auc": [float(d_auc.mean()), *np.percentile(d_auc[boot].mean(1), [2.5, 97.5]).tolist()],
        }
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tools/peaks_check.py", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--dataset", required=True)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--target", action="append", help="scene/image/instance, e.g. 1/5/1; repeat")
    c.add_argument("--scenes", type=int, nargs="*")
    c.add_argument("--max-images", type=int)
    c.add_argument("--score", default="thesis")
    c.add_argument("--weights", default="auto")
    r = sub.add_parser("refine")
    r.add_argument("pool", type=Path)
    r.add_argument("--out", type=Path)
    r.add_argument("--peaks", type=int, nargs="+", default=[1, 2, 4, 8])
    r.add_argument("--yaws", type=int, nargs="+", default=[1, 2, 3])
    r.add_argument("--separation", type=int, nargs="+", default=[3])
    r.add_argument("--weights", default="auto")
    args = p.parse_args(argv)
    collect(args) if args.cmd == "collect" else refine_all(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
