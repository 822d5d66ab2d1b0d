"""`python -m perch_warp bench`: time the reference workload (workload.py) and the ray-casting
microbenchmark with its peer (raycast.py); write OUT/bench.json and OUT/bench.txt."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

from ..errors import PerchError
from ..pose_error import add_s
from ..result import SearchInfo
from ..score_terms import DEFAULT_SCORE
from .environment import command_line, device_name, device_peak_mib, git_commit, git_dirty, host_peak_mib
from .raycast import AGREEMENT_MIN, time_raycast
from .workload import Workload, add_frame_arguments, default_dataset, load_workload, search_camera

STAGES = (
    "photo_features",
    "rarity",
    "candidates",
    "bound",
    "render",
    "features_score",
    "transfer",
    "reduction",
    "refine",
    "total",
)


def time_search(engine, w: Workload, repeat: int, warmup: int = 1) -> tuple[dict, SearchInfo]:
    """`warmup` untimed estimates, then `repeat` timed ones: per-stage times (s), throughput, the pose and
    its ADD-S; and the last run's SearchInfo (which renderer and conv form ran)."""
    if repeat < 1 or warmup < 0:
        raise PerchError(f"--repeat must be at least 1 and --warmup at least 0, got {repeat} and {warmup}")
    args = (w.image, w.camera, w.table, w.resting, w.space)
    warm = None
    for _ in range(warmup):
        t0 = time.perf_counter()
        res = engine.estimate(*args)
        warm = {"wall_s": time.perf_counter() - t0, "timings_s": dict(res.timings_s)}
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = engine.estimate(*args)
        runs.append({"wall_s": time.perf_counter() - t0, "timings_s": dict(res.timings_s)})
    stages = [s for s in STAGES if any(s in r["timings_s"] for r in runs)]
    mean = {s: float(np.mean([r["timings_s"].get(s, 0.0) for r in runs])) for s in stages}
    best = {s: float(np.min([r["timings_s"].get(s, 0.0) for r in runs])) for s in stages}
    wall = float(np.mean([r["wall_s"] for r in runs]))
    evaluated = res.info.evaluated
    rays = res.info.rays
    b = res.best
    gx, gy, gyaw = w.truth_xy_yaw
    summary = {
        "space": w.space.describe(),
        "candidates_in_space": int(res.n_candidates),
        "candidates_evaluated": evaluated,
        "candidates_scored": int(res.n_scored),
        "rays_per_run": rays,
        "batches": res.info.batches,
        "threads": res.info.threads,
        "repeat": repeat,
        "warmup": warm,
        "runs": runs,
        "timings_s_mean": mean,
        "timings_s_min": best,
        "wall_s_mean": wall,
        "candidates_per_s": evaluated / wall if wall > 0 else None,
        # Per thread where several CPU threads render at once (the render stage is then their summed time).
        "rays_per_s_render": rays / mean["render"] if mean.get("render", 0.0) > 0 else None,
        "refine": res.info.extra.get("refine"),
        "pose": {"x_m": b.x_m, "y_m": b.y_m, "yaw_rad": b.yaw_rad, "score": b.score},
        "truth": {"x_m": gx, "y_m": gy, "yaw_rad": gyaw},
        "adds_m": add_s(b.T_m2c[:3, :3], b.T_m2c[:3, 3], w.R_gt, w.t_gt_m, w.adds_points_m),
    }
    return summary, res.info


def _rate(v: float | None, unit: str) -> str:
    if v is None:
        return "-"
    for scale, prefix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= scale:
            return f"{v / scale:.3g} {prefix}{unit}"
    return f"{v:.3g} {unit}"


def format_report(r: dict) -> str:
    """bench.txt: the figures of `r` (bench.json's content) as a readable table."""
    lines = _settings_lines(r) + _stage_lines(r["search"]) + _result_lines(r) + _raycast_lines(r)
    return "\n".join(lines)


def _settings_lines(r: dict) -> list[str]:
    """Where and what was measured: device, commit, command, workload and settings; the stage table's head."""
    s = r["search"]
    dirty = {True: " (with uncommitted changes)", False: "", None: ""}[r.get("git_dirty")]
    return [
        "perch_warp bench",
        f"device        {r['device_name']}",
        f"commit        {r['commit']}{dirty}",
        f"command       {r['command']}",
        f"warp          {r['warp_version']}, weights: {r['weights']}",
        f"workload      {r['workload']} (table: {r['table_source']})",
        f"search        {r['settings']['search']}, image scale {r['settings']['image_scale']:g} "
        f"({r['search_image'][0]}x{r['search_image'][1]} px)",
        f"renderer      {r['settings'].get('renderer', 'bvh')}"
        + (" (back faces skipped: closed mesh)" if r["settings"].get("cull_back_faces") else ""),
        f"conv1         {r['settings'].get('conv', 'warp')}",
        f"space         {s['space']}",
        f"setup         {r['setup_s']:.2f} s (engine: mesh upload, kernel build; not timed below)",
        f"warm-up run   {s['warmup']['wall_s']:.3f} s (excluded from the figures below)"
        if s["warmup"]
        else "warm-up run   none (--warmup 0: the kernels were built at setup)",
        "",
        f"{'stage':<16}{'mean s':>11}{'min s':>11}{'share':>8}   ({s['repeat']} timed run{'s' * (s['repeat'] > 1)})",
    ]


def _stage_lines(s: dict) -> list[str]:
    """Seconds per stage of the timed runs (mean, min, share) and the wall time."""
    lines = []
    threads = s.get("threads", 1)
    stage_times = {k: v for k, v in s["timings_s_mean"].items() if k != "total"}
    # With several threads the stages overlap: shares are of their summed (CPU) time, not of the wall time.
    tot = sum(stage_times.values()) if threads > 1 else s["timings_s_mean"].get("total", 0.0)
    for stage, v in s["timings_s_mean"].items():
        share = f"{100 * v / tot:7.1f}%" if tot > 0 and stage != "total" else ""
        lines.append(f"{stage:<16}{v:>11.4f}{s['timings_s_min'][stage]:>11.4f}{share:>8}")
    lines.append(f"{'wall (estimate)':<16}{s['wall_s_mean']:>11.4f}")
    if threads > 1:
        lines.append(
            f"              {threads} CPU threads score batches at once: render, features_score, reduction and "
            "transfer are CPU seconds summed over them (shares of the stages' sum); total is wall time"
        )
    return lines


def _result_lines(r: dict) -> list[str]:
    """What the search scored, how fast, its refinement, memory, and the pose against the truth."""
    s = r["search"]
    threads = s.get("threads", 1)
    gx, gy = s["truth"]["x_m"], s["truth"]["y_m"]
    p = s["pose"]
    lines = [
        "",
        f"candidates    {s['candidates_in_space']} in the space, {s['candidates_evaluated']} evaluated, "
        f"{s['candidates_scored']} scored",
        f"throughput    {_rate(s['candidates_per_s'], 'candidates/s')} (evaluated / wall), "
        f"{_rate(s['rays_per_s_render'], 'rays/s')} (rays / render stage{', per thread' if threads > 1 else ''})",
        f"rays          {s['rays_per_run']:,} pixels ray-cast per run, {s['batches']} batch(es)",
    ]
    ref = s.get("refine")
    if ref:
        lines.append(
            f"refinement    cell of the best grid pose at {ref['step_xy_m'] * 1000:.3g} mm / {ref['step_yaw_deg']:.3g} "
            f"deg: {ref['evaluated']:,} of {ref['candidates']:,} poses scored, {ref['rays']:,} rays (not in the "
            f"figures above), score {ref['score_gain']:+.4f}"
            + (f"; {len(ref['peaks'])} peaks refined" if ref.get("peaks") else "")
        )
    m = r["memory"]
    dev = (
        f"{m['device_peak_mib']:.1f} MiB ({m['device_note']})" if m["device_peak_mib"] is not None else m["device_note"]
    )
    lines.append(f"memory        host peak {m['host_peak_mib']:.1f} MiB (ru_maxrss), device {dev}")
    lines.append(
        f"pose found    x {p['x_m']:+.4f} m, y {p['y_m']:+.4f} m, yaw {math.degrees(p['yaw_rad']):.1f} deg "
        f"(truth x {gx:+.4f} m, y {gy:+.4f} m, yaw {math.degrees(s['truth']['yaw_rad']):.1f} deg); "
        f"ADD-S {s['adds_m'] * 100:.2f} cm"
    )
    return lines


def _raycast_lines(r: dict) -> list[str]:
    """The microbenchmark and its peer: rays per second, agreement."""
    rc = r["raycast"]
    wst = rc["warp"]
    lines = [
        "",
        f"ray casting   one ray per pixel, {rc['poses']} poses in view, {rc['image'][0]}x{rc['image'][1]} px each, "
        f"{100 * rc['hit_fraction']:.1f} % of rays hit",
        f"  warp        {_rate(wst['rays_per_s'], 'rays/s')} on {r['device']} ({wst['launches']} launches of "
        f"{wst['rays_per_launch']:,} rays in {wst['seconds']:.3f} s; warm-up {wst['warmup_s']:.3f} s"
        + (f"; {wst['cpu_busy_cores']:.2f} cores busy)" if wst.get("cpu_busy_cores") is not None else ")"),
    ]
    peer = rc["peer"]
    if "skipped" in peer:
        lines.append(f"  {peer['skipped']}")
    else:
        ok = "ok" if peer["agreement_ok"] else f"FAILED: below {100 * AGREEMENT_MIN:g} %"
        med = peer["depth_abs_diff_median_m"]
        lines += [
            f"  open3d      {_rate(peer['rays_per_s'], 'rays/s')} ({peer['name']} {peer['version']}, "
            f"{peer['launches']} calls in {peer['seconds']:.3f} s; {peer['cpu_busy_cores']:.2f} cores busy)",
            f"  warp/open3d {peer['warp_over_peer']:.3g}x",
            f"  agreement   hit/miss equal on {100 * peer['agreement']:.3f} % of {peer['rays']:,} rays "
            f"({peer['disagreeing_rays']} differ; {ok})"
            + (
                f"; depth |diff| median {med:.2e} m, max {peer['depth_abs_diff_max_m']:.2e} m"
                if med is not None
                else ""
            ),
        ]
    return lines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `python -m perch_warp bench` (defaults: the reference workload)."""
    w = parser.add_argument_group("workload (default: the reference workload)")
    add_frame_arguments(w)
    w.add_argument("--split", default="test", help="split folder (default: test)")
    w.add_argument("--clip", type=float, default=1.0, help="visible table clipped to a square this wide, m (default 1)")
    w.add_argument("--xy-step", type=float, default=0.01, help="x/y step, m (default: 0.01)")
    w.add_argument("--yaw-step", type=float, default=0.1, help="yaw step over the full circle, rad (default: 0.1)")
    m = parser.add_argument_group("engine")
    m.add_argument("--device", default=None, help="Warp device: cpu | cuda:0 (default: a GPU if Warp sees one)")
    m.add_argument("--weights", default="caffe", help="conv1 weights: caffe | torchvision | auto | FILE.npz")
    m.add_argument("--search", default="exhaustive", choices=["exhaustive", "pruned", "coarse-to-fine"])
    m.add_argument(
        "--renderer",
        default="auto",
        choices=["auto", "bvh", "raster"],
        help="kernel #1's form: bvh or raster (same images); auto: by faces per box pixel on the CPU, bvh on a GPU",
    )
    m.add_argument(
        "--conv",
        default="auto",
        choices=["auto", "warp", "torch"],
        help="kernel #2's conv1: warp or torch (same values up to rounding); auto: torch on the CPU, warp on a GPU "
        "unless the score has the centre term",
    )
    m.add_argument("--image-scale", type=float, default=1.0, help="search on the photo resized by this factor")
    m.add_argument(
        "--score",
        default=DEFAULT_SCORE,
        metavar="NAME|TERMS",
        help=f"the score, as the CLI's --score (default: {DEFAULT_SCORE})",
    )
    m.add_argument("--cpu-threads", type=int, default=None, help="CPU device: batches at once (default: one per core)")
    m.add_argument(
        "--refine",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="search the best grid pose's cell at 2 mm / 1 deg, as the CLI does (default: on)",
    )
    m.add_argument(
        "--refine-peaks", type=int, default=1, help="refine this many distinct grid peaks, as the CLI (default: 1)"
    )
    m.add_argument(
        "--refine-yaws", type=int, default=1, help="refine this many yaws of each peak's place, as the CLI (default: 1)"
    )
    b = parser.add_argument_group("benchmark")
    b.add_argument("--repeat", type=int, default=1, help="timed runs after the warm-up runs (default: 1)")
    b.add_argument(
        "--warmup",
        type=int,
        default=1,
        help="untimed runs first (default: 1; 0 for long CPU runs: setup builds kernels)",
    )
    b.add_argument("--ray-poses", type=int, default=8, help="poses in the ray-casting microbenchmark (default: 8)")
    b.add_argument(
        "--min-time", type=float, default=1.0, help="microbenchmark: repeat launches for at least this many s (1)"
    )
    b.add_argument("--no-peer", action="store_true", help="skip the Open3D peer of the microbenchmark")
    b.add_argument("--out", type=Path, default=Path("perch_warp_bench"), help="folder for bench.json and bench.txt")


def _checked_dataset(args: argparse.Namespace) -> Path:
    """The dataset folder, once the benchmark's own options are checked (before any work)."""
    dataset = args.dataset or default_dataset()
    if dataset is None:
        raise PerchError("no --dataset given and shared/data/ycbv not found (set PERCH_WARP_SHARED)")
    if args.repeat < 1 or args.ray_poses < 1 or args.warmup < 0:
        raise PerchError(
            f"--repeat and --ray-poses must be at least 1 and --warmup at least 0, "
            f"got {args.repeat}, {args.ray_poses} and {args.warmup}"
        )
    if not (math.isfinite(args.min_time) and args.min_time >= 0):
        raise PerchError(f"--min-time must be a non-negative number of seconds, got {args.min_time}")
    return dataset


def _settings(args: argparse.Namespace, dataset: Path, info: SearchInfo, config, threads: int) -> dict:
    """bench.json's "settings": the workload and engine options, and what --renderer/--conv auto chose."""
    return {
        "dataset": str(Path(dataset).resolve()),
        "split": args.split,
        "scene": args.scene,
        "image": args.image,
        "obj": args.obj,
        "clip_m": args.clip,
        "xy_step_m": args.xy_step,
        "yaw_step_rad": args.yaw_step,
        "search": args.search,
        "refine": args.refine,
        "refine_peaks": args.refine_peaks,
        "refine_yaws": args.refine_yaws,
        "score": info.score,
        "renderer": info.renderer,
        "renderer_option": args.renderer,
        "cull_back_faces": info.cull_back_faces,
        "conv": info.conv,
        "conv_option": args.conv,
        "image_scale": args.image_scale,
        "cpu_threads": threads,
        "stride_px": config.stride,
        "alpha": config.alpha,
        "clusters": config.clusters,
    }


def run(args: argparse.Namespace) -> int:
    """Entry point of `python -m perch_warp bench`; PerchError propagates to the CLI."""
    # Imported here: the engine imports torch (seconds), which `bench --help` does not need.
    from ..engine import Engine, EngineConfig, default_device
    from ..features import load_feature_weights

    dataset = _checked_dataset(args)
    # validates before any work
    config = EngineConfig(
        search=args.search,
        image_scale=args.image_scale,
        cpu_threads=args.cpu_threads,
        refine=args.refine,
        refine_peaks=args.refine_peaks,
        refine_yaws=args.refine_yaws,
        renderer=args.renderer,
        conv=args.conv,
        score=args.score,
    )
    w = load_workload(dataset, args.scene, args.image, args.obj, args.clip, args.xy_step, args.yaw_step, args.split)
    weights = load_feature_weights(args.weights)
    device = args.device or default_device()
    engine = Engine(w.mesh, weights, device, config)
    threads = engine.cpu_threads()
    on = f"{device}" + (f" ({threads} CPU threads)" if threads > 1 else "")
    print(f"bench: {w.label}; {w.space.describe()} on {on}", file=sys.stderr, flush=True)
    search, info = time_search(engine, w, args.repeat, args.warmup)
    host_peak = host_peak_mib()  # before the microbenchmark and peer, so it is the search's
    dev_peak, dev_note = device_peak_mib(device)
    raycast = time_raycast(engine, w, args.image_scale, args.ray_poses, args.min_time, peer=not args.no_peer)
    cam = search_camera(w.camera, args.image_scale)
    report = {
        "device": device,
        "device_name": device_name(device),
        "commit": git_commit(),
        "git_dirty": git_dirty(),
        "command": command_line(),
        "warp_version": wp.__version__,
        "weights": weights.source,
        "workload": w.label,
        "table_source": w.table_source,
        "settings": _settings(args, dataset, info, config, threads),
        "search_image": [cam.width, cam.height],
        "setup_s": engine.setup_s,
        "search": search,
        "memory": {"host_peak_mib": host_peak, "device_peak_mib": dev_peak, "device_note": dev_note},
        "raycast": raycast,
    }
    text = format_report(report)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(report, indent=1) + "\n")
    (out / "bench.txt").write_text(text + "\n")
    print(text)
    print(f"wrote {out / 'bench.json'} and {out / 'bench.txt'}", file=sys.stderr)
    return 0
