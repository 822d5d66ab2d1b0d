"""How the search cost grows with the table size (clip), the x/y step and the image scale.

Small exhaustive searches on `perch_warp bench`'s reference frame and object (ycbv
test scene 2 image 1, obj 9; visible table clipped to a square, never placed by the
ground truth), yaw step 30 deg, one sweep per factor with the other two at their base
values (--base-clip 0.1 m, --base-xy 0.02 m, --base-scale 0.5):

  clip         --clips 0.05 0.1 0.15 0.2 (m)
  x/y step     --xy-steps 0.04 0.02 0.01 0.005 (m)
  image scale  --scales 0.25 0.5 0.75 1.0

A point shared by sweeps runs once. Per image scale one engine is built and warmed up
on the smallest point; each point then runs --repeat times and keeps the fastest run.
"search s" is the time of the stages that scale with the candidates (candidates,
render, features_score, transfer, reduction); the per-photo stages (photo_features,
rarity) are kept in the JSON.

Writes OUT/scaling.json and OUT/scaling.png (search time against candidates and against rays).

    python tools/scaling.py [--device cpu] [--out perch_warp_scaling]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

from perch_warp.bench import Workload, add_frame_arguments, default_dataset, device_name, git_commit, load_workload
from perch_warp.engine import Engine, EngineConfig, default_device
from perch_warp.errors import PerchError
from perch_warp.eval import protocol
from perch_warp.features import load_feature_weights

PER_CANDIDATE_STAGES = ("candidates", "render", "features_score", "transfer", "reduction")
SWEEPS = ("clip", "xy_step", "image_scale")


def plan(args: argparse.Namespace) -> list[dict]:
    """The points to measure: (clip m, xy step m, image scale) and the sweeps each belongs to."""
    base = (args.base_clip, args.base_xy, args.base_scale)
    points: dict[tuple[float, float, float], set[str]] = {}
    for sweep, values in zip(SWEEPS, (args.clips, args.xy_steps, args.scales), strict=True):
        for v in values:
            key = tuple(v if i == SWEEPS.index(sweep) else b for i, b in enumerate(base))
            points.setdefault(key, set()).add(sweep)
    return [{"clip_m": c, "xy_step_m": s, "image_scale": k, "sweeps": sorted(sw)} for (c, s, k), sw in points.items()]


def measure(engine: Engine, w: Workload, repeat: int) -> dict:
    """The fastest of `repeat` searches: wall and stage times (s), candidates and rays."""
    best = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        r = engine.estimate(w.image, w.camera, w.table, w.resting, w.space)
        wall = time.perf_counter() - t0
        if best is None or wall < best[0]:
            best = (wall, r)
    wall, r = best
    search_s = sum(r.timings_s.get(s, 0.0) for s in PER_CANDIDATE_STAGES)
    return {
        "space": w.space.describe(),
        "candidates": int(r.n_candidates),
        "evaluated": r.info.evaluated,
        "rays": r.info.rays,
        "wall_s": wall,
        "search_s": search_s,
        "timings_s": dict(r.timings_s),
        "candidates_per_s": r.info.evaluated / search_s if search_s > 0 else None,
        "rays_per_s_render": r.info.rays / r.timings_s["render"] if r.timings_s.get("render", 0) > 0 else None,
        # auto picks these per search (the renderer by faces per box pixel), so they can change along a sweep
        "renderer": r.info.renderer,
        "conv": r.info.conv,
        "threads": r.info.threads,
    }


def plot(path: Path, rows: list[dict], title: str) -> None:
    """Two log-log panels: search time against candidates evaluated, and against rays cast; one series per sweep."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3))
    labels = {"clip": "clip (table size)", "xy_step": "x/y step", "image_scale": "image scale"}
    keys = {"clip": "clip_m", "xy_step": "xy_step_m", "image_scale": "image_scale"}
    fmt = {"clip": lambda v: f"{v:g} m", "xy_step": lambda v: f"{100 * v:g} cm", "image_scale": lambda v: f"x{v:g}"}
    for k, sweep in enumerate(SWEEPS):
        # In the order of the swept value: points of an image-scale sweep share one candidate count.
        pts = sorted((r for r in rows if sweep in r["sweeps"]), key=lambda r, key=keys[sweep]: r[key])
        if not pts:
            continue
        for ax, xkey in zip(axes, ("evaluated", "rays"), strict=True):
            ax.plot([p[xkey] for p in pts], [p["search_s"] for p in pts], "o-", color=f"C{k}", label=labels[sweep])
            for p in pts:
                ax.annotate(
                    fmt[sweep](p[keys[sweep]]),
                    (p[xkey], p["search_s"]),
                    fontsize=7,
                    xytext=(3, 3 + 9 * k),  # a point shared by sweeps gets one label per sweep
                    textcoords="offset points",
                )
    threads = max(r.get("threads", 1) for r in rows)
    ylabel = "search time (s)" if threads <= 1 else f"search time (CPU s, summed over {threads} threads)"
    axes[0].set(xscale="log", yscale="log", xlabel="candidates evaluated", ylabel=ylabel)
    axes[1].set(xscale="log", yscale="log", xlabel="rays cast (rendered pixels)", ylabel=ylabel)
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        w0, points, device, engines = _setup(args)
    except PerchError as e:
        print(f"scaling: error: {e}", file=sys.stderr)
        return 1

    print(f"device {device_name(device)}, commit {git_commit()}, {w0.label}")
    print(
        f"{'sweeps':<26}{'clip m':>7}{'xy m':>6}{'scale':>6}{'cands':>8}{'rays':>12}{'search s':>10}{'wall s':>8}"
        "  renderer"
    )
    smallest = min(points, key=lambda p: len(p["workload"].space))["workload"]
    for engine in engines.values():
        engine.estimate(smallest.image, smallest.camera, smallest.table, smallest.resting, smallest.space)  # warm-up
    rows = []
    for p in sorted(points, key=lambda p: (p["image_scale"], len(p["workload"].space))):
        m = measure(engines[p["image_scale"]], p.pop("workload"), args.repeat)
        row = {**p, **m}
        rows.append(row)
        print(
            f"{','.join(row['sweeps']):<26}{row['clip_m']:>7g}{row['xy_step_m']:>6g}{row['image_scale']:>6g}"
            f"{row['evaluated']:>8}{row['rays']:>12,}{row['search_s']:>10.3f}{row['wall_s']:>8.3f}  {row['renderer']}",
            flush=True,
        )
    _write(args, device, w0, rows)
    return 0


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_frame_arguments(ap)
    ap.add_argument("--device", default=None, help="cpu | cuda:0 (default: a GPU if Warp sees one)")
    ap.add_argument("--weights", default="caffe")
    ap.add_argument("--yaw-step", type=float, default=math.radians(30.0), help="rad (default: 30 deg)")
    ap.add_argument("--base-clip", type=float, default=0.1, help="m")
    ap.add_argument("--base-xy", type=float, default=0.02, help="m")
    ap.add_argument("--base-scale", type=float, default=0.5)
    ap.add_argument("--clips", type=float, nargs="+", default=[0.05, 0.1, 0.15, 0.2], help="m")
    ap.add_argument("--xy-steps", type=float, nargs="+", default=[0.04, 0.02, 0.01, 0.005], help="m")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.25, 0.5, 0.75, 1.0])
    ap.add_argument("--repeat", type=int, default=1, help="runs per point; the fastest is kept (default 1)")
    ap.add_argument("--out", type=Path, default=Path("perch_warp_scaling"), help="folder for scaling.json/.png")
    return ap


def _setup(args: argparse.Namespace):
    """(base workload, the points each with its workload, device, an engine per image scale), every
    point's space validated before any search; PerchError when one cannot be had."""
    if args.repeat < 1:
        raise PerchError(f"--repeat must be at least 1, got {args.repeat}")
    dataset = args.dataset or default_dataset()
    if dataset is None:
        raise PerchError("no --dataset given and shared/data/ycbv not found (set PERCH_WARP_SHARED)")
    points = plan(args)
    w0 = load_workload(dataset, args.scene, args.image, args.obj, args.base_clip, args.base_xy, args.yaw_step)
    for p in points:
        space_fn = protocol.visible_table_space(p["xy_step_m"], args.yaw_step, p["clip_m"])
        p["workload"] = dataclasses.replace(w0, space=space_fn(w0.camera, w0.table, w0.resting))
        len(p["workload"].space)  # validates every point before any search
    weights = load_feature_weights(args.weights)
    device = args.device or default_device()
    engines = {
        k: Engine(w0.mesh, weights, device, EngineConfig(image_scale=k, search="exhaustive", refine=False))
        for k in {p["image_scale"] for p in points}
    }
    return w0, points, device, engines


def _write(args: argparse.Namespace, device: str, w0: Workload, rows: list[dict]) -> None:
    """OUT/scaling.json (the settings and every point) and OUT/scaling.png."""
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "device": device,
        "device_name": device_name(device),
        "commit": git_commit(),
        "workload": w0.label,
        "yaw_step_rad": args.yaw_step,
        "base": {"clip_m": args.base_clip, "xy_step_m": args.base_xy, "image_scale": args.base_scale},
        "repeat": args.repeat,
        "search_stages": list(PER_CANDIDATE_STAGES),
    }
    (out / "scaling.json").write_text(json.dumps({**meta, "points": rows}, indent=1) + "\n")
    title = (
        f"{w0.label} on {meta['device_name']}, commit {meta['commit']}, yaw step {math.degrees(args.yaw_step):g} deg"
    )
    plot(out / "scaling.png", rows, title)
    print(f"wrote {out / 'scaling.json'} and {out / 'scaling.png'}")


if __name__ == "__main__":
    sys.exit(main())
