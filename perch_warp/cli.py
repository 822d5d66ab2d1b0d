"""Command line: `python -m perch_warp IMAGE --mesh MESH --camera CAMERA.json ...` and subcommands.

Subcommands: `demo` (a self-made scene, offline), `eval` (BOP datasets), `synth`
(synthetic BOP scenes), `bench` (speed measurements). Bad input ends with one line on stderr and exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import re
import sys
from pathlib import Path

from .errors import PerchError

# name -> module exposing add_arguments(parser) and run(args) -> int
SUBCOMMANDS = {
    "demo": ("perch_warp.demo", "run the whole pipeline on a scene the project makes itself (offline)"),
    "eval": ("perch_warp.eval.command", "evaluate on a BOP-format dataset (ADD-S, AUC, plots)"),
    "synth": ("perch_warp.synth", "generate photorealistic synthetic BOP test scenes"),
    "bench": ("perch_warp.bench", "time the reference workload, a ray-casting microbenchmark and its Open3D peer"),
}


# Host bytes a search keeps per candidate of its grid, counted from the arrays of engine.py (not
# measured): the pruned search holds a bound, a score and a box size (3 x 8 B) for every candidate, and
# while sorting the bounds their negation, the order, the finite mask and the ranked bounds (8 + 8 + 1 +
# 8 + 8 B): 57 B, rounded up to 64. Poses, boxes and renderings are set up a chunk/batch at a time, so
# they do not grow with the grid. See docs/reliability.md.
BYTES_PER_CANDIDATE = 64
DEFAULT_MAX_CANDIDATES = 50_000_000  # 3.2 GB at BYTES_PER_CANDIDATE; the reference workload has 485,604


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --- options shared by the estimate, demo and eval commands -------------------------------------


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
        default="thesis",
        metavar="NAME|TERMS",
        help="what a candidate's score is made of: thesis (the thesis's formula), or terms over it such as "
        "surround=fill,background=0.5,shrink=16 (perch_warp/score_terms.py; default: thesis)",
    )
    g.add_argument(
        "--search",
        default="auto",
        choices=["auto", "exhaustive", "pruned", "coarse-to-fine"],
        help="score every grid pose; or only those whose silhouette bound can reach the best (same answer); "
        "or a coarse lattice refined around the best; auto: pruned on the CPU, exhaustive on a GPU (default)",
    )
    g.add_argument("--coarse-xy", type=float, default=0.02, help="coarse-to-fine: first lattice's x/y step, m")
    g.add_argument("--coarse-yaw", type=float, default=10.0, help="coarse-to-fine: first lattice's yaw step, deg")
    g.add_argument("--beam", type=int, default=32, help="coarse-to-fine: candidates refined per level (default 32)")
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
        "auto (default): torch on the CPU, warp on a GPU",
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
    )


def search_space_from_args(args: argparse.Namespace, camera, table):
    from .search_space import SearchSpace

    yaw_lo, yaw_hi = (math.radians(a) for a in args.yaw_range)
    if args.x_range is None and args.y_range is None:
        space = SearchSpace.visible_table(camera, table, args.xy_step, math.radians(args.yaw_step), clip_m=args.clip)
        space = SearchSpace(
            space.x_range_m, space.y_range_m, args.xy_step, (yaw_lo, yaw_hi), math.radians(args.yaw_step)
        )
        check_search_size(space, getattr(args, "max_candidates", DEFAULT_MAX_CANDIDATES))
        return space
    if args.x_range is None or args.y_range is None:
        raise PerchError("give both --x-range and --y-range, or neither (then the visible table is searched)")
    space = SearchSpace(
        tuple(args.x_range), tuple(args.y_range), args.xy_step, (yaw_lo, yaw_hi), math.radians(args.yaw_step)
    )
    check_search_size(space, getattr(args, "max_candidates", DEFAULT_MAX_CANDIDATES))  # validates ranges and steps
    return space


def build_engine(args: argparse.Namespace, mesh, quiet: bool = False):
    """Weights, device and engine from the method options, saying what was chosen."""
    from .engine import Engine, default_device
    from .features import load_feature_weights

    config = engine_config_from_args(args)
    weights = load_feature_weights(args.weights)
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


def renderer_line(result) -> str:
    """Which form of kernel #1 ran and why (the option, the device and rule, back faces skipped or not)."""
    from .render import RASTER_FACES_PER_PIXEL

    info = result.info
    method = info["renderer"]
    why = ""
    if info.get("renderer_option") == "auto":
        why = f" (auto on {result.device}"
        if "median_box_px" in info:
            rel = "<=" if method == "raster" else ">"
            why += (
                f": {info['mesh_faces']:,} faces {rel} {RASTER_FACES_PER_PIXEL} x the median candidate box, "
                f"{info['median_box_px']:,.0f} px"
            )
        why += ")"
    if method == "raster":
        faces = "closed mesh: back faces skipped" if info["cull_back_faces"] else "open mesh: every face tested"
        return f"renderer: raster{why}, {faces}"
    return f"renderer: bvh{why}"


def conv_line(result) -> str:
    """Which form of kernel #2's convolution ran, and whether auto chose it."""
    info = result.info
    how = {"torch": "torch conv2d on each candidate's crop", "warp": "Warp kernel, point by point"}[info["conv"]]
    why = f" (auto on {result.device})" if info.get("conv_option") == "auto" else ""
    return f"features: conv1 by {how}{why}; score: {info.get('score', 'thesis')}"


def write_json_atomic(path: str | Path, data: dict) -> None:
    from .outputs import atomic_write_text

    atomic_write_text(path, json.dumps(data, indent=1))


# --- the main job: estimate one image -----------------------------------------------------------


def add_estimate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("image", help="RGB photo (PNG/JPEG)")
    p.add_argument("--mesh", required=True, help="object mesh: textured OBJ, PLY with vertex colours, PLY/GLB with UVs")
    p.add_argument(
        "--mesh-units", default="auto", choices=["auto", "mm", "m"], help="mesh length unit (default: auto by size)"
    )
    p.add_argument(
        "--untextured",
        action="store_true",
        help="search a mesh that has no material and no vertex colours at all in uniform grey (silhouette only)",
    )
    p.add_argument(
        "--camera", required=True, help="camera JSON: BOP scene_camera.json style (cam_K, cam_R_w2c, cam_t_w2c in mm)"
    )
    p.add_argument(
        "--image-id",
        type=int,
        default=None,
        help="entry of a multi-image scene_camera.json (default: from the image name)",
    )
    p.add_argument(
        "--lift-mm", type=float, default=0.0, help="the surface the object stands on is this high above the table (mm)"
    )
    p.add_argument(
        "--truth",
        default=None,
        help="BOP scene_gt.json: take height, roll and pitch from the ground truth of --obj-id (thesis protocol) "
        "and report the estimate's error",
    )
    p.add_argument("--obj-id", type=int, default=None, help="object id in --truth")
    add_search_arguments(p)
    add_method_arguments(p)
    g = p.add_argument_group("output")
    g.add_argument("--out", default=None, help="write the result as JSON here")
    g.add_argument("--overlay", default=None, help="write a PNG of the best pose over the photo here")
    g.add_argument("--quiet", action="store_true", help="no progress bar or notes on stderr")


def _image_id(args: argparse.Namespace) -> int | None:
    if args.image_id is not None:
        return args.image_id
    m = re.fullmatch(r"0*(\d+)", Path(args.image).stem)
    return int(m.group(1)) if m else None


def run_estimate(args: argparse.Namespace) -> int:
    from .bop import read_camera_json, truth_instance
    from .camera import camera_from_entry
    from .image import image_header_size, load_rgb, save_png
    from .mesh import load_mesh
    from .outputs import check_output_file
    from .table import RestingPose, Table, decompose_on_table

    # Everything is checked before any work: options, output paths, then the inputs from the cheapest.
    engine_config_from_args(args)
    if args.out:
        check_output_file(args.out, "--out")
    if args.overlay:
        check_output_file(args.overlay, "--overlay")
    width, height = image_header_size(args.image)
    image_id = _image_id(args)
    try:
        entry = read_camera_json(args.camera, image_id)
    except PerchError:
        if args.image_id is None and image_id is not None:
            entry = read_camera_json(args.camera, None)
        else:
            raise
    camera = camera_from_entry(entry, width, height, source=args.camera, image=args.image)
    table = Table.from_entry(entry, source=args.camera)
    truth = None
    if args.truth or args.obj_id is not None:
        if not args.truth:
            raise PerchError("--obj-id needs --truth (a BOP scene_gt.json)")
        g = truth_instance(args.truth, args.image_id if args.image_id is not None else image_id, args.obj_id)
        try:
            resting, gx, gy, gyaw = decompose_on_table(table, g.R_m2c, g.t_m2c_m)
        except PerchError as e:
            raise PerchError(f"ground truth {args.truth}: {e}") from None
        truth = (g.R_m2c, g.t_m2c_m, gx, gy, gyaw)
    mesh = load_mesh(args.mesh, args.mesh_units, untextured=args.untextured)
    if truth is None:
        resting = RestingPose.upright(mesh.vertices_m, lift_m=args.lift_mm / 1000.0)
    space = search_space_from_args(args, camera, table)
    image = load_rgb(args.image)
    if image.shape[:2] != (height, width):  # the file changed since its header was read
        raise PerchError(f"image {args.image} changed while being read")
    if not args.quiet:
        log(f"mesh: {mesh.source}, units {mesh.units_note}, {len(mesh.faces)} faces")
        log(f"search: {space.describe()}")
    engine = build_engine(args, mesh, args.quiet)
    result = engine.estimate(image, camera, table, resting, space, progress=not args.quiet)
    out = {
        "image": str(args.image),
        "mesh": str(args.mesh),
        "resting": {"R_rest": resting.R_rest.reshape(-1).tolist(), "z_m": resting.z_m},
    }
    out.update(result.to_dict())
    b = result.best
    print(
        f"pose: x = {b.x_m:+.4f} m, y = {b.y_m:+.4f} m, yaw = {math.degrees(b.yaw_rad):.1f} deg (table frame), "
        f"score {b.score:.4f}"
    )
    print(timing_line(result))
    print(search_summary(result))
    print(renderer_line(result))
    print(conv_line(result))
    if truth is not None:
        from .pose_error import add, adi

        R_gt, t_gt, gx, gy, gyaw = truth
        pts = mesh.vertices_m
        err = {
            "x_m": gx,
            "y_m": gy,
            "yaw_deg": math.degrees(gyaw),
            "adds_m": adi(b.T_m2c[:3, :3], b.T_m2c[:3, 3], R_gt, t_gt, pts),
            "add_m": add(b.T_m2c[:3, :3], b.T_m2c[:3, 3], R_gt, t_gt, pts),
            "xy_error_m": math.hypot(b.x_m - gx, b.y_m - gy),
            "yaw_error_deg": abs(math.degrees((b.yaw_rad - gyaw + math.pi) % (2 * math.pi) - math.pi)),
        }
        out["truth"] = err
        print(
            f"truth: x = {gx:+.4f} m, y = {gy:+.4f} m, yaw = {math.degrees(gyaw):.1f} deg; "
            f"ADD-S {err['adds_m'] * 100:.2f} cm, ADD {err['add_m'] * 100:.2f} cm, "
            f"xy error {err['xy_error_m'] * 100:.2f} cm, yaw error {err['yaw_error_deg']:.1f} deg"
        )
    if args.out:
        write_json_atomic(args.out, out)
    if args.overlay:
        from .overlay import TRUTH_COLOR, caption, overlay_mask, overlay_rendering

        rgb, mask = engine.render(camera, b.T_m2c)
        pic = overlay_rendering(image, rgb, mask)
        lines = [
            f"estimate (magenta): x {b.x_m:+.3f} m  y {b.y_m:+.3f} m  "
            f"yaw {math.degrees(b.yaw_rad):.0f} deg  score {b.score:.3f}"
        ]
        if truth is not None:
            from .table import pose_matrix

            _, gmask = engine.render(camera, pose_matrix(truth[0], truth[1]))
            pic = overlay_mask(pic, gmask & ~mask, TRUTH_COLOR, tint=0.0)
            from .overlay import mask_contour

            pic[mask_contour(gmask)] = TRUTH_COLOR
            lines.append(f"ground truth (green): ADD-S {out['truth']['adds_m'] * 100:.2f} cm")
        save_png(args.overlay, caption(pic, lines))
    return 0


def timing_line(result) -> str:
    """Seconds per stage; with several CPU threads the per-batch stages overlap, and the line says so."""
    line = "time: " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings_s.items())
    threads = result.info.get("threads", 1)
    if threads > 1:
        line += f" (batch stages: CPU s summed over {threads} threads; total: wall)"
    return line


def search_summary(result) -> str:
    """One line: how many of the space's candidates the search scored, and why not all."""
    info = result.info
    chosen = f" (auto on {result.device})" if info.get("search_option") == "auto" else ""
    line = f"search: {info['search']}{chosen}, scored {info['evaluated']:,} of {result.n_candidates:,} candidates"
    if info["search"] == "pruned":
        k = info["k"]  # not len(top_k): the refined pose may replace a runner-up
        if info["evaluated"] < info["bounded"]:
            line += f" ({info['bounded']:,} bounded by their silhouettes; the rest cannot reach the top {k})"
        else:
            line += f" (every silhouette bound reached the top {k}: nothing pruned)"
    elif info["search"] == "coarse-to-fine":
        line += " (a pyramid: may miss the exhaustive optimum)"
    ref = info.get("refine")
    if ref is not None:
        line += (
            f"; refined below the grid: the best pose's cell at {ref['step_xy_m'] * 1000:.3g} mm / "
            f"{ref['step_yaw_deg']:.3g}° ({ref['evaluated']:,} of {ref['candidates']:,} poses scored, "
            f"score {ref['score_gain']:+.4f})"
        )
    return line


# --- entry point --------------------------------------------------------------------------------


def _parser(prog: str = "python -m perch_warp") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Find where a known object sits on a table from one RGB image (PERCH Color Only on NVIDIA Warp). "
        f"Subcommands: {', '.join(SUBCOMMANDS)} (see `{prog} SUBCOMMAND --help`).",
    )
    add_estimate_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in SUBCOMMANDS:
            module_name, help_text = SUBCOMMANDS[argv[0]]
            p = argparse.ArgumentParser(prog=f"python -m perch_warp {argv[0]}", description=help_text)
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            return int(module.run(p.parse_args(argv[1:])) or 0)
        return run_estimate(_parser().parse_args(argv))
    except PerchError as e:
        log("perch_warp: error: " + " ".join(str(e).split()))  # always one line
        return 1
    except KeyboardInterrupt:
        log("perch_warp: interrupted")
        return 130
