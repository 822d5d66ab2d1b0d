"""Options shared by the estimate, demo and eval commands: the method and search-space arguments, their
validation, and the engine and search space built from them."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from .errors import PerchError
from .joint import DEFAULT_PEAKS
from .report import log
from .score_terms import DEFAULT_SCORE
from .search_space import SearchSpace

# Host bytes a search keeps per candidate of its grid, counted from the arrays of engine.py (not
# measured): the pruned search holds a bound, a score and a box size (3 x 8 B) for every candidate, and
# while sorting the bounds their negation, the order, the finite mask and the ranked bounds (8 + 8 + 1 +
# 8 + 8 B): 57 B, rounded up to 64. Poses, boxes and renderings are set up a chunk/batch at a time, so
# they do not grow with the grid. See docs/reliability.md.
BYTES_PER_CANDIDATE = 64


DEFAULT_MAX_CANDIDATES = 50_000_000  # 3.2 GB at BYTES_PER_CANDIDATE; the reference workload has 485,604


def add_method_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("method (thesis §3.2)")
    g.add_argument(
        "--weights", default="auto", help="conv1 weights: auto | caffe | torchvision | FILE.npz (default: auto)"
    )
    g.add_argument("--stride", type=int, default=4, help="feature-grid stride in pixels (default: 4)")
    g.add_argument(
        "--alpha", type=float, default=0.5, help="occlusion limit α in (0, 1]: mean of the top α of pixel scores"
    )
    g.add_argument("--clusters", type=int, default=20, help="k-means clusters for rarity (default: 20)")
    g.add_argument("--seed", type=int, default=0, help="k-means seed (default: 0)")
    g.add_argument("--top-k", type=int, default=5, help="how many best poses to report (default: 5)")
    g.add_argument("--relu", action="store_true", help="apply AlexNet's ReLU after conv1 (default: raw conv1)")
    g.add_argument(
        "--score",
        default=DEFAULT_SCORE,
        metavar="NAME|TERMS",
        help="what a candidate's score is made of: centred-direction (= shift=1,centre=0.5,inits=4,"
        "cluster=direction: centred-4starts, the photo's rarity clustered on the direction of conv1's "
        "response, so how lit a window is does not make it rare), centred-4starts (= shift=1,centre=0.5,"
        "inits=4: centred, the photo's rarity from the best of four k-means starts), centred (= shift=1,"
        "centre=0.5: the pattern "
        "inside the silhouette counts beside its colours, and the grid stage tolerates a one-cell "
        "misalignment), grid-tolerant (= shift=1, the thesis's formula with that grid stage), thesis (the "
        "thesis's formula exactly), or terms over the thesis's such as surround=fill,background=0.5,shrink=16 "
        f"(perch_warp/score_terms.py; default: {DEFAULT_SCORE})",
    )
    _add_search_method_arguments(g)
    _add_compute_arguments(g)


def _add_search_method_arguments(g) -> None:
    """Which search, its coarse-to-fine lattice and the refinement below the grid."""
    g.add_argument(
        "--search",
        default="auto",
        choices=["auto", "exhaustive", "pruned", "coarse-to-fine"],
        help="score every grid pose; or only those whose silhouette bound can reach the best (same answer); "
        "or a coarse lattice refined around the best; auto: pruned on the CPU, exhaustive on a GPU (default)",
    )
    g.add_argument("--coarse-xy", type=float, default=0.02, help="coarse-to-fine: first lattice's x/y step, m")
    g.add_argument("--coarse-yaw", type=float, default=10.0, help="coarse-to-fine: first lattice's yaw step, deg")
    g.add_argument("--beam", type=int, default=512, help="coarse-to-fine: candidates refined per level (default 512)")
    g.add_argument(
        "--refine",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="search the best grid pose's cell (one grid step either side) at --refine-xy and --refine-yaw "
        "(default: on)",
    )
    g.add_argument("--refine-xy", type=float, default=0.002, help="refinement's x/y step at most, m (default: 0.002)")
    g.add_argument("--refine-yaw", type=float, default=1.0, help="refinement's yaw step at most, deg (default: 1)")
    g.add_argument(
        "--refine-cells",
        type=int,
        default=1,
        help="grid steps either side of the best grid pose that the refinement searches (default: 1; "
        "2 catches narrow score peaks between grid poses at about 7x the cost)",
    )
    g.add_argument(
        "--refine-peaks",
        type=int,
        default=1,
        help="refine this many distinct peaks of the grid search and keep the best refined pose (default: 1, "
        "the grid's best only; more recovers small objects whose narrow peak loses on the grid)",
    )
    g.add_argument(
        "--refine-yaws",
        type=int,
        default=1,
        help="refine this many distinct yaws of each refined peak's place (default: 1, its best grid yaw; "
        "more: every grid yaw there is scored and its best local maxima are refined too)",
    )


def _add_compute_arguments(g) -> None:
    """Where and how the kernels run: image scale, device, renderer, conv form, batches, threads."""
    g.add_argument(
        "--image-scale",
        type=float,
        default=1.0,
        help="search on the photo resized by this factor in (0, 1], e.g. 0.5 for 4x fewer rays (default: 1)",
    )
    g.add_argument("--device", default=None, help="Warp device: cpu | cuda:0 (default: a GPU if Warp sees one)")
    g.add_argument(
        "--renderer",
        default="auto",
        choices=["auto", "bvh", "raster"],
        help="how rays find the mesh: bvh (Warp's mesh query per ray) or raster (each triangle tests the rays "
        "it covers; the same images); auto (default): on the CPU raster unless the mesh has over 3 faces per "
        "pixel of a candidate's box, on a GPU bvh",
    )
    g.add_argument(
        "--conv",
        default="auto",
        choices=["auto", "warp", "torch"],
        help="how candidates' conv1 features are computed: warp (in the scoring kernel, point by point) or "
        "torch (conv2d on each candidate's composited crop; the same values up to float rounding); "
        "auto (default): torch on the CPU, warp on a GPU unless the score has the centre term",
    )
    g.add_argument(
        "--batch-pixels", type=int, default=None, help="rendered pixels per batch (default: sized to the device)"
    )
    g.add_argument(
        "--cpu-threads",
        type=int,
        default=None,
        help="CPU device: batches scored at once (default: one per available core; same scores for any number)",
    )


def add_search_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("search space (table frame)")
    g.add_argument(
        "--x-range", type=float, nargs=2, metavar=("LO", "HI"), help="x range in metres (default: visible table)"
    )
    g.add_argument(
        "--y-range", type=float, nargs=2, metavar=("LO", "HI"), help="y range in metres (default: visible table)"
    )
    g.add_argument("--xy-step", type=float, default=0.01, help="x/y step in metres (default: 0.01)")
    g.add_argument(
        "--yaw-range", type=float, nargs=2, default=(0.0, 360.0), metavar=("LO", "HI"), help="degrees (default: 0 360)"
    )
    g.add_argument("--yaw-step", type=float, default=5.0, help="yaw step in degrees (default: 5)")
    g.add_argument(
        "--clip", type=float, default=1.0, help="default region: visible table clipped to a square this wide (m)"
    )
    g.add_argument(
        "--max-candidates",
        type=int,
        default=DEFAULT_MAX_CANDIDATES,
        help=f"refuse a search space with more grid poses than this, before any work (default: "
        f"{DEFAULT_MAX_CANDIDATES:,}, about {DEFAULT_MAX_CANDIDATES * BYTES_PER_CANDIDATE / 1e9:.1f} GB; "
        "raise it for larger searches that fit in memory)",
    )


def _finite(name: str, value: float, positive: bool = False) -> None:
    if not math.isfinite(value) or (positive and value <= 0):
        raise PerchError(f"{name} must be a {'positive ' if positive else ''}finite number, got {value}")


def validate_options(args: argparse.Namespace) -> None:
    """Every numeric option of the method and the search space, before any file is read (one rule per
    option, shared by the estimate, demo and eval commands; EngineConfig checks the method's own values)."""
    for name in ("xy_step", "yaw_step", "clip", "coarse_xy", "coarse_yaw", "refine_xy", "refine_yaw"):
        if hasattr(args, name):
            _finite("--" + name.replace("_", "-"), getattr(args, name), positive=True)
    for name in ("x_range", "y_range", "yaw_range"):
        for v in getattr(args, name, None) or ():
            _finite("--" + name.replace("_", "-"), v)
    if getattr(args, "lift_mm", None) is not None:
        _finite("--lift-mm", args.lift_mm)
    if args.batch_pixels is not None and args.batch_pixels < 1:
        raise PerchError(f"--batch-pixels must be a positive number of pixels, got {args.batch_pixels}")
    # Beyond a feature window (11 px for AlexNet's conv1) the grid skips pixels: with 32 px an object
    # of 100 px keeps ~9 feature points, and much coarser grids leave most objects none.
    if not 1 <= args.stride <= MAX_STRIDE:
        raise PerchError(f"--stride must be 1..{MAX_STRIDE} pixels, got {args.stride}")
    if getattr(args, "max_candidates", 1) < 1:
        raise PerchError(f"--max-candidates must be at least 1, got {args.max_candidates}")


MAX_STRIDE = 32


class SearchTooLarge(PerchError):
    """A search space beyond --max-candidates or the memory available: an option problem, not a target's."""


def _available_memory_bytes() -> int | None:
    """MemAvailable from /proc/meminfo (Linux), None elsewhere."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_search_size(space, max_candidates: int) -> int:
    """The space's candidate count, refused before any work when it exceeds max_candidates or the memory
    that BYTES_PER_CANDIDATE says it needs is not available. Counted from the axes (never materialised)."""
    # Counted from the ranges first: the axes of a huge space (--xy-step 1e-6) would not fit in memory.
    (x0, x1), (y0, y1), (a0, a1) = space.x_range_m, space.y_range_m, space.yaw_range_rad
    rough = [(hi - lo) / step + 1 for lo, hi, step in ((x0, x1, space.xy_step_m), (y0, y1, space.xy_step_m))]
    rough.append(min(a1 - a0, 2 * math.pi) / space.yaw_step_rad + 1)
    n = math.prod(rough) if math.prod(rough) > 2 * max_candidates else len(space)
    need = n * BYTES_PER_CANDIDATE
    what = (
        f"the search space has {'about ' if not isinstance(n, int) else ''}{n:,.0f} candidates "
        f"(x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m step {space.xy_step_m:g} m, yaw step "
        f"{math.degrees(space.yaw_step_rad):g} deg), needing about {need / 1e9:.3g} GB"
    )
    if n > max_candidates:
        raise SearchTooLarge(
            f"{what}: more than --max-candidates {max_candidates:,}; narrow --x-range/--y-range, coarsen "
            "--xy-step/--yaw-step, or raise --max-candidates if the memory is there"
        )
    avail = _available_memory_bytes()
    if avail is not None and need > avail:
        raise SearchTooLarge(f"{what}, more than the {avail / 1e9:.1f} GB of memory available: narrow or coarsen it")
    return int(n)


def engine_config_from_args(args: argparse.Namespace):
    # Imported here: Warp and torch take seconds, and the CLI imports this module for every command (synth too).
    from .engine import EngineConfig

    validate_options(args)
    return EngineConfig(
        stride=args.stride,
        alpha=args.alpha,
        clusters=args.clusters,
        seed=args.seed,
        top_k=args.top_k,
        relu=args.relu,
        score=args.score,
        batch_pixels=args.batch_pixels,
        search=args.search,
        renderer=args.renderer,
        conv=args.conv,
        coarse_xy_m=args.coarse_xy,
        coarse_yaw_rad=math.radians(args.coarse_yaw),
        beam=args.beam,
        image_scale=args.image_scale,
        cpu_threads=args.cpu_threads,
        refine=args.refine,
        refine_xy_m=args.refine_xy,
        refine_yaw_rad=math.radians(args.refine_yaw),
        refine_cells=args.refine_cells,
        refine_peaks=args.refine_peaks,
        refine_yaws=args.refine_yaws,
    )


def search_space_from_args(args: argparse.Namespace, camera, table):

    yaw_lo, yaw_hi = (math.radians(a) for a in args.yaw_range)
    if args.x_range is None and args.y_range is None:
        space = SearchSpace.visible_table(camera, table, args.xy_step, math.radians(args.yaw_step), clip_m=args.clip)
        x_range, y_range = _within_extent(space, table)
        space = SearchSpace(x_range, y_range, args.xy_step, (yaw_lo, yaw_hi), math.radians(args.yaw_step))
        check_search_size(space, getattr(args, "max_candidates", DEFAULT_MAX_CANDIDATES))
        return space
    if args.x_range is None or args.y_range is None:
        raise PerchError("give both --x-range and --y-range, or neither (then the visible table is searched)")
    space = SearchSpace(
        tuple(args.x_range), tuple(args.y_range), args.xy_step, (yaw_lo, yaw_hi), math.radians(args.yaw_step)
    )
    check_search_size(space, getattr(args, "max_candidates", DEFAULT_MAX_CANDIDATES))  # validates ranges and steps
    return space


def _within_extent(space, table) -> tuple[tuple[float, float], tuple[float, float]]:
    """The visible region's x and y ranges cut to the table extent's bounding box (snapped outwards to the
    grid step), when the table has an extent; refused in one line when the two do not meet."""
    if table.extent_m is None:
        return space.x_range_m, space.y_range_m
    step = space.xy_step_m
    lo = np.floor(table.extent_m.min(axis=0) / step) * step
    hi = np.ceil(table.extent_m.max(axis=0) / step) * step
    (x0, x1), (y0, y1) = space.x_range_m, space.y_range_m
    x_range, y_range = (max(x0, lo[0]), min(x1, hi[0])), (max(y0, lo[1]), min(y1, hi[1]))
    if x_range[0] > x_range[1] or y_range[0] > y_range[1]:
        raise PerchError(
            f"the table extent (x {lo[0]:+.3f}..{hi[0]:+.3f} m, y {lo[1]:+.3f}..{hi[1]:+.3f} m) lies outside the "
            f"visible table ({space.describe()})"
        )
    return (float(x_range[0]), float(x_range[1])), (float(y_range[0]), float(y_range[1]))


def table_with_extent(args: argparse.Namespace, table):
    """The table with --table-extent X0 X1 Y0 Y1 (a rectangle, metres, table frame) when given; it replaces
    any table_extent_mm of the camera file."""
    extent = getattr(args, "table_extent", None)
    if extent is None:
        return table
    x0, x1, y0, y1 = extent
    if not (x0 < x1 and y0 < y1):
        raise PerchError(f"--table-extent takes X0 X1 Y0 Y1 with X0 < X1 and Y0 < Y1 (metres), got {extent}")
    return table.with_extent([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def add_joint_peaks_argument(p, when: str) -> None:
    """--joint-peaks, for the image command (several objects) and eval (--joint); `when` says which."""
    p.add_argument(
        "--joint-peaks",
        type=int,
        default=DEFAULT_PEAKS,
        help=f"{when}: each object's best distinct peaks (refined) the joint step chooses among "
        f"(default: {DEFAULT_PEAKS}; at least --refine-peaks)",
    )


def add_occluders_argument(p, when: str) -> None:
    """--occluders, for the image command (several objects) and eval (--joint); `when` says which. Left
    out it is None: `resolve_occluders` makes it "answers" where several objects are searched, "none"
    otherwise (the development screen read at stop 61 chose the second pass for several objects)."""
    p.add_argument(
        "--occluders",
        choices=("none", "answers"),
        default=None,
        help=f"{when}: 'answers' (the default) searches each object a second time with the other objects' "
        "answers as occluders: its points they cover, nearer the camera, are left out of its score "
        "(perch_warp.hidden); the second search re-scores only the candidates they can hide "
        "(perch_warp.search.known); 'none': one pass",
    )


def resolve_occluders(args: argparse.Namespace, several: bool, needs: str) -> str:
    """args.occluders made definite: left out, "answers" with several objects and "none" with one;
    "answers" asked for where one object is searched is an error that says what it `needs`."""
    if args.occluders is None:
        args.occluders = "answers" if several else "none"
    elif args.occluders != "none" and not several:
        raise PerchError(f"--occluders {args.occluders} needs {needs}")
    return args.occluders


def build_engine(args: argparse.Namespace, mesh, quiet: bool = False, config=None, weights=None):
    """Weights, device and engine from the method options (or the `config` and loaded `weights` given),
    saying what was chosen."""
    from .engine import Engine, default_device  # as in engine_config_from_args
    from .features import load_feature_weights

    config = config or engine_config_from_args(args)
    weights = weights or load_feature_weights(args.weights)
    device = args.device or default_device()
    engine = Engine(mesh, weights, device, config)
    if not quiet:
        log(f"features: {weights.source}")
        threads = engine.cpu_threads()
        log(
            f"device: {device}"
            + ("" if args.device else " (chosen automatically; --device to override)")
            + (f", {threads} CPU threads (--cpu-threads to change)" if threads > 1 else "")
        )
    return engine
