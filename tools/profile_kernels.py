"""Per-kernel times of one search on the chosen device (a small fixed workload on the reference frame).

The workload is `perch_warp bench`'s reference frame and object (ycbv test scene 2
image 1, obj 9) over a small region: the visible table clipped to --clip (0.1 m),
--xy-step 2 cm, --yaw-step 0.5 rad. One warm-up search (kernel builds, caches) runs
first and is not profiled; then one search is profiled:

- cpu (or --method sync): every `wp.launch` is timed on the host and followed by
  `wp.synchronize_device`, so a launch's time includes its argument packing;
- cuda (--method events, the default there): Warp's CUDA activity timing
  (`wp.timing_begin(TIMING_KERNEL | TIMING_KERNEL_BUILTIN | TIMING_MEMCPY | TIMING_MEMSET)`),
  i.e. device-side times of kernels, copies and fills, without host overhead.

Prints kernel -> calls, total ms, mean ms, share of the summed activity, and the
search's wall time beside it (the rest is host work: k-means, boxes, top-α, Python).

    python tools/profile_kernels.py [--device cpu|cuda:0] [--clip 0.1] [--image-scale 1] [--out profile.json]
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections import defaultdict
from pathlib import Path

import warp as wp

from perch_warp.bench import add_frame_arguments, default_dataset, device_name, git_commit, load_workload
from perch_warp.engine import Engine, EngineConfig, default_device
from perch_warp.errors import PerchError
from perch_warp.features import load_feature_weights

CUDA_ACTIVITY = wp.TIMING_KERNEL | wp.TIMING_KERNEL_BUILTIN | wp.TIMING_MEMCPY | wp.TIMING_MEMSET


def kernel_label(name: str) -> str:
    """A readable kernel name: no `outer__locals__` prefix (kernels made in a function), no 8-hex module hash."""
    name = re.sub(r"\S*__locals__", "", name)
    return re.sub(r"_[0-9a-f]{8}$", "", name)


def profile_sync(run, device: str) -> tuple[dict[str, list[float]], float]:
    """Run `run()` with every wp.launch timed on the host (ms per call, by kernel key) and synchronised."""
    times: dict[str, list[float]] = defaultdict(list)
    original = wp.launch

    def timed_launch(kernel, *args, **kwargs):
        wp.synchronize_device(kwargs.get("device") or device)
        t0 = time.perf_counter()
        out = original(kernel, *args, **kwargs)
        wp.synchronize_device(kwargs.get("device") or device)
        times[kernel_label(getattr(kernel, "key", str(kernel)))].append(1e3 * (time.perf_counter() - t0))
        return out

    wp.launch = timed_launch  # the engine calls `wp.launch` through the module, so this reaches every launch
    try:
        t0 = time.perf_counter()
        run()
        wall_ms = 1e3 * (time.perf_counter() - t0)
    finally:
        wp.launch = original
    return dict(times), wall_ms


def profile_events(run) -> tuple[dict[str, list[float]], float]:
    """Run `run()` under Warp's CUDA activity timing: device ms per kernel, copy and fill, by name."""
    times: dict[str, list[float]] = defaultdict(list)
    wp.timing_begin(cuda_filter=CUDA_ACTIVITY)
    t0 = time.perf_counter()
    try:
        run()
    finally:
        wall_ms = 1e3 * (time.perf_counter() - t0)
        results = wp.timing_end()
    for r in results:
        times[kernel_label(r.name)].append(float(r.elapsed))
    return dict(times), wall_ms


def format_table(times: dict[str, list[float]], wall_ms: float) -> str:
    """kernel -> calls, total ms, mean ms, share of the summed times; most expensive first."""
    total = sum(sum(v) for v in times.values())
    width = max([len("kernel")] + [len(k) for k in times]) + 2
    lines = [f"{'kernel':<{width}}{'calls':>7}{'total ms':>12}{'mean ms':>12}{'share':>9}"]
    lines.append("-" * len(lines[0]))
    for name, v in sorted(times.items(), key=lambda kv: -sum(kv[1])):
        share = f"{100 * sum(v) / total:8.1f}%" if total > 0 else "        -"
        lines.append(f"{name:<{width}}{len(v):>7}{sum(v):>12.3f}{sum(v) / len(v):>12.3f}{share}")
    lines.append("-" * len(lines[0]))
    lines.append(f"{'sum':<{width}}{sum(len(v) for v in times.values()):>7}{total:>12.3f}")
    pct = f" (the timed activity is {100 * total / wall_ms:.1f} % of it)" if wall_ms > 0 else ""
    lines.append(f"search wall time {wall_ms:.3f} ms{pct}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        w, device, engine, method = _setup(args)
    except PerchError as e:
        print(f"profile_kernels: error: {e}", file=sys.stderr)
        return 1

    def run() -> None:
        engine.estimate(w.image, w.camera, w.table, w.resting, w.space)

    run()  # warm-up: kernel builds and first-call costs stay out of the profile
    times, wall_ms = profile_events(run) if method == "events" else profile_sync(run, device)
    head = [
        f"device   {device_name(device)}",
        f"commit   {git_commit()}, warp {wp.__version__}",
        f"workload {w.label}; {w.space.describe()}; image scale {args.image_scale:g}, {args.search}",
        f"method   {method}: "
        + (
            "CUDA activity timing (device time)" if method == "events" else "host timer around each synchronised launch"
        ),
        "",
    ]
    text = "\n".join(head) + format_table(times, wall_ms)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(_figures(args, device, w, method, times, wall_ms), indent=1) + "\n")
    return 0


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_frame_arguments(ap)
    ap.add_argument("--clip", type=float, default=0.1, help="visible table clipped to this square, m (default 0.1)")
    ap.add_argument("--xy-step", type=float, default=0.02, help="m (default 0.02)")
    ap.add_argument("--yaw-step", type=float, default=0.5, help="rad (default 0.5)")
    ap.add_argument("--image-scale", type=float, default=1.0)
    ap.add_argument("--search", default="exhaustive", choices=["exhaustive", "pruned", "coarse-to-fine"])
    ap.add_argument("--device", default=None, help="cpu | cuda:0 (default: a GPU if Warp sees one)")
    ap.add_argument("--weights", default="caffe")
    ap.add_argument(
        "--method",
        default="auto",
        choices=["auto", "sync", "events"],
        help="sync: host timer around each launch; events: CUDA activity timing (default: events on CUDA, else sync)",
    )
    ap.add_argument("--out", type=Path, default=None, help="also write the figures as JSON here")
    return ap


def _setup(args: argparse.Namespace):
    """(workload, device, engine, timing method) of the options; PerchError when one cannot be had."""
    dataset = args.dataset or default_dataset()
    if dataset is None:
        raise PerchError("no --dataset given and shared/data/ycbv not found (set PERCH_WARP_SHARED)")
    w = load_workload(dataset, args.scene, args.image, args.obj, args.clip, args.xy_step, args.yaw_step)
    device = args.device or default_device()
    engine = Engine(
        w.mesh,
        load_feature_weights(args.weights),
        device,
        EngineConfig(search=args.search, image_scale=args.image_scale),
    )
    method = args.method if args.method != "auto" else ("events" if device.startswith("cuda") else "sync")
    if method == "events" and not device.startswith("cuda"):
        raise PerchError("--method events needs a CUDA device (CUDA activity timing)")
    return w, device, engine, method


def _figures(args: argparse.Namespace, device: str, w, method: str, times: dict, wall_ms: float) -> dict:
    """What --out writes: the device, commit, workload and settings, and the profile."""
    return {
        "device": device,
        "device_name": device_name(device),
        "commit": git_commit(),
        "warp_version": wp.__version__,
        "workload": w.label,
        "space": w.space.describe(),
        "settings": {
            "clip_m": args.clip,
            "xy_step_m": args.xy_step,
            "yaw_step_rad": args.yaw_step,
            "yaw_step_deg": math.degrees(args.yaw_step),
            "image_scale": args.image_scale,
            "search": args.search,
        },
        "method": method,
        "search_wall_ms": wall_ms,
        "kernels_ms": times,
    }


if __name__ == "__main__":
    sys.exit(main())
