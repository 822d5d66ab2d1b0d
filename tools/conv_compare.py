"""Kernel #2's conv1 in its two forms on the same rendered boxes: the Warp kernel (point by point)
against torch's conv2d on each candidate's composited crop (zero-copy through `wp.to_torch`).

    python tools/conv_compare.py [--device cpu|cuda:0] [--poses 300] [--seed 0] [--repeat 3] [--out conv.json]

Poses drawn at random from the reference workload's grid (ycbv test scene 2 image 1, potted
meat can, visible table clipped to 1 m, 1 cm / 0.1 rad, the real photo), rendered once by the
device's default form of kernel #1; then `FeatureScorer.score_points` runs on that batch with
each conv form, each timed after a warm-up call, best of --repeat. Reports the feature points,
how many are on the mask, the time per on-mask point and the largest difference of the two
forms' values (cos x rarity). On the CPU torch runs on one thread, as the engine runs it (one
thread per batch). `--conv auto` picks from these figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp
from perch_warp.kernels.features import NOT_ON_MASK

from perch_warp.bench import (
    add_frame_arguments,
    add_pose_sample_arguments,
    default_dataset,
    device_name,
    git_commit,
    load_workload,
    sample_grid_poses,
)
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.features import load_feature_weights
from perch_warp.score import grid_boxes


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    dataset = args.dataset or default_dataset()
    if dataset is None:
        print("conv_compare: shared/data/ycbv not found (set PERCH_WARP_SHARED)", file=sys.stderr)
        return 1
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    w = load_workload(dataset, args.scene, args.image, args.obj, 1.0, 0.01, 0.1)
    try:
        weights = load_feature_weights(args.weights)
        # grid-tolerant: the default score's centre term runs in the torch form alone (score_terms: centre).
        engines = {
            conv: Engine(w.mesh, weights, args.device, EngineConfig(conv=conv, score="grid-tolerant"))
            for conv in ("warp", "torch")
        }
    except PerchError as e:
        print(f"conv_compare: error: {e}", file=sys.stderr)
        return 1
    e = engines["warp"]
    photo = e.scoring(w.image, w.camera, w.table, w.resting).photo
    R, t, boxes = sample_grid_poses(w, args.poses, args.seed, lambda R, t: e.boxes(w.camera, R, t))
    gboxes = grid_boxes(boxes, weights.kernel_size, e.config.stride)
    renderer = "raster" if wp.get_device(args.device).is_cpu else "bvh"
    batch = e.renderer_for(renderer).render(w.camera, R, t, boxes)
    times, values = _time_forms(engines, photo, batch, gboxes, args)
    report = _report(times, values, weights, args.device, w.label, renderer, len(boxes))
    _print_report(report)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0 if report["same_points_on_mask"] else 1


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_frame_arguments(ap)
    add_pose_sample_arguments(ap)
    ap.add_argument("--device", default="cpu", help="Warp device (default: cpu)")
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per form, best kept (default 3)")
    ap.add_argument("--weights", default="caffe")
    ap.add_argument("--out", type=Path, default=None, help="write the figures here as JSON")
    return ap


def _time_forms(engines: dict, photo, batch, gboxes: np.ndarray, args) -> tuple[dict, dict]:
    """Per conv form (its engine's scorer): the best of args.repeat timed score_points calls on the batch
    after a warm-up (kernel builds, torch's first call), and the values that warm-up scored."""
    times, values = {}, {}
    for conv, eng in engines.items():
        scorer = eng.scorer

        def call(scorer=scorer):
            out, _ = scorer.score_points(photo.image, batch, gboxes, photo.obs, photo.norm, photo.weights)
            wp.synchronize_device(args.device)
            return out

        with scorer.conv_settings():
            values[conv] = call().numpy()  # warm-up: kernel builds, torch's first call
            best = float("inf")
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                call()
                best = min(best, time.perf_counter() - t0)
        times[conv] = best
    return times, values


def _report(times: dict, values: dict, weights, device: str, label: str, renderer: str, n_cand: int) -> dict:
    """The figures: each form's time, per on-mask point and as conv1 arithmetic throughput, and whether
    the two forms score the same points (and how far apart their values are)."""
    on = values["warp"] > NOT_ON_MASK / 2
    same_mask = bool(np.array_equal(on, values["torch"] > NOT_ON_MASK / 2))
    diff = float(np.abs(values["warp"][on] - values["torch"][on]).max()) if on.any() else 0.0
    n_on = int(on.sum())
    # conv1's multiply-adds, against a core's peak, say how much of a form's time is arithmetic.
    # torch's conv2d convolves every feature point of a crop; the Warp kernel only those on the mask.
    per_point = 2.0 * weights.channels * 3 * weights.kernel_size**2 / 1e9
    gflop = {"warp": per_point * n_on, "torch": per_point * len(on)}
    return {
        "device": device,
        "device_name": device_name(device),
        "commit": git_commit(),
        "workload": label,
        "renderer": renderer,
        "candidates": n_cand,
        "feature_points": len(on),
        "on_mask_points": n_on,
        "seconds": times,
        "us_per_on_mask_point": {k: 1e6 * v / max(n_on, 1) for k, v in times.items()},
        "torch_over_warp": times["torch"] / times["warp"],
        "conv1_gflop": gflop,
        "gflop_per_s": {k: gflop[k] / v for k, v in times.items()},
        "same_points_on_mask": same_mask,
        "max_abs_difference": diff,
    }


def _print_report(report: dict) -> None:
    times, gflop = report["seconds"], report["conv1_gflop"]
    print(f"device   {report['device_name']}\ncommit   {report['commit']}")
    print(f"batch    {report['candidates']} candidates of {report['workload']} ({report['renderer']} render)")
    print(f"points   {report['feature_points']:,} feature points, {report['on_mask_points']:,} on the mask")
    for conv in ("warp", "torch"):
        print(
            f"{conv:<8} {times[conv]:.4f} s  {report['us_per_on_mask_point'][conv]:.3f} us per on-mask point, "
            f"{report['gflop_per_s'][conv]:.1f} GFLOP/s of conv1 arithmetic ({gflop[conv]:.2f} GFLOP)"
        )
    print(f"torch / warp {report['torch_over_warp']:.2f}; same points on the mask: {report['same_points_on_mask']}")
    print(f"largest |difference| of the values: {report['max_abs_difference']:.2e}")


if __name__ == "__main__":
    sys.exit(main())
