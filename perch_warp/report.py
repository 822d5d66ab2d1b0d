"""What the commands print about a search: the chosen renderer, conv form and score, the timings and how
much of the space was scored; and notes on stderr."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from .outputs import atomic_write_text


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def renderer_line(result) -> str:
    """Which form of kernel #1 ran and why (the option, the device and rule, back faces skipped or not)."""
    from .render import RASTER_FACES_PER_PIXEL  # imports Warp: not at the top, which the CLI imports for every command

    info = result.info
    method = info.renderer
    why = ""
    if info.renderer_option == "auto":
        why = f" (auto on {result.device}"
        if info.median_box_px is not None:
            rel = "<=" if method == "raster" else ">"
            why += (
                f": {info.mesh_faces:,} faces {rel} {RASTER_FACES_PER_PIXEL} x the median candidate box, "
                f"{info.median_box_px:,.0f} px"
            )
        why += ")"
    if method == "raster":
        faces = "closed mesh: back faces skipped" if info.cull_back_faces else "open mesh: every face tested"
        return f"renderer: raster{why}, {faces}"
    return f"renderer: bvh{why}"


def conv_line(result) -> str:
    """Which form of kernel #2's convolution ran, and whether auto chose it."""
    info = result.info
    how = {"torch": "torch conv2d on each candidate's crop", "warp": "Warp kernel, point by point"}[info.conv]
    why = ""
    if info.conv_option == "auto":
        gpu_torch = info.conv == "torch" and not result.device.startswith("cpu")
        why = f" (auto on {result.device}" + (": the score's centre term needs it)" if gpu_torch else ")")
    return f"features: conv1 by {how}{why}; score: {info.score}"


def write_json_atomic(path: str | Path, data: dict) -> None:

    atomic_write_text(path, json.dumps(data, indent=1))


def timing_line(result) -> str:
    """Seconds per stage; with several CPU threads the per-batch stages overlap, and the line says so."""
    line = "time: " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings_s.items())
    threads = result.info.threads
    if threads > 1:
        line += f" (batch stages: CPU s summed over {threads} threads; total: wall)"
    return line


def search_summary(result) -> str:
    """One line: how many of the space's candidates the search scored, and why not all."""
    info = result.info
    chosen = f" (auto on {result.device})" if info.search_option == "auto" else ""
    line = f"search: {info.search}{chosen}, scored {info.evaluated:,} of {result.n_candidates:,} candidates"
    if info.search == "pruned":
        k = info.extra["k"]  # not len(top_k): the refined pose may replace a runner-up
        if info.evaluated < info.extra["bounded"]:
            line += f" ({info.extra['bounded']:,} bounded by their silhouettes; the rest cannot reach the top {k})"
        else:
            line += f" (every silhouette bound reached the top {k}: nothing pruned)"
    elif info.search == "coarse-to-fine":
        line += " (a pyramid: may miss the exhaustive optimum)"
    ref = info.extra.get("refine")
    if ref is not None:
        line += (
            f"; refined below the grid: the best pose's cell at {ref['step_xy_m'] * 1000:.3g} mm / "
            f"{ref['step_yaw_deg']:.3g}° ({ref['evaluated']:,} of {ref['candidates']:,} poses scored, "
            f"score {ref['score_gain']:+.4f})"
        )
    return line
