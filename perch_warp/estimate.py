"""The main command, `python -m perch_warp IMAGE --mesh MESH --camera CAMERA.json`: estimate one image."""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

from .bop import read_camera_json, truth_instance
from .camera import camera_from_entry
from .errors import PerchError
from .image import image_header_size, load_rgb, save_png
from .mesh import load_mesh
from .options import (
    add_method_arguments,
    add_search_arguments,
    build_engine,
    engine_config_from_args,
    search_space_from_args,
)
from .outputs import check_output_file
from .overlay import TRUTH_COLOR, caption, mask_contour, overlay_mask, overlay_rendering
from .pose_error import add, adi
from .report import conv_line, log, renderer_line, search_summary, timing_line, write_json_atomic
from .table import RestingPose, Table, decompose_on_table, pose_matrix


def _image_id(args: argparse.Namespace) -> int | None:
    if args.image_id is not None:
        return args.image_id
    m = re.fullmatch(r"0*(\d+)", Path(args.image).stem)
    return int(m.group(1)) if m else None


def run(args: argparse.Namespace) -> int:
    """Entry point of the main command; PerchError propagates to the CLI."""

    # Everything is checked before any work: options, output paths, then the inputs from the cheapest.
    engine_config_from_args(args)
    if args.out:
        check_output_file(args.out, "--out")
    if args.overlay:
        check_output_file(args.overlay, "--overlay")
    if args.heatmap:
        check_output_file(args.heatmap, "--heatmap")
    width, height = image_header_size(args.image)
    image_id = _image_id(args)
    entry = _camera_entry(args, image_id)
    camera = camera_from_entry(entry, width, height, source=args.camera, image=args.image)
    table = Table.from_entry(entry, source=args.camera)
    truth, resting = _read_truth(args, image_id, table)
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
    print(result.confidence.line())
    print(timing_line(result))
    print(search_summary(result))
    print(renderer_line(result))
    print(conv_line(result))
    if truth is not None:
        out["truth"] = _truth_error(truth, b, mesh.vertices_m)
    if args.out:
        write_json_atomic(args.out, out)
    if args.overlay:
        _write_overlay(args.overlay, engine, image, camera, b, truth, out)
    if args.heatmap:
        from .heatmap import write_heatmap  # matplotlib: imported only when a heat map is asked for

        write_heatmap(args.heatmap, image, camera, table, result, None if truth is None else truth[2:4])
    return 0


def _camera_entry(args: argparse.Namespace, image_id: int | None) -> dict:
    """The camera entry for the image: by --image-id, else by the image name's number, else the file's only one."""
    try:
        return read_camera_json(args.camera, image_id)
    except PerchError:
        if args.image_id is None and image_id is not None:
            return read_camera_json(args.camera, None)
        raise


def _read_truth(args: argparse.Namespace, image_id: int | None, table: Table):
    """(R_gt, t_gt, x, y, yaw) and the resting pose from --truth/--obj-id, or (None, None) without them."""
    if not (args.truth or args.obj_id is not None):
        return None, None
    if not args.truth:
        raise PerchError("--obj-id needs --truth (a BOP scene_gt.json)")
    g = truth_instance(args.truth, args.image_id if args.image_id is not None else image_id, args.obj_id)
    try:
        resting, gx, gy, gyaw = decompose_on_table(table, g.R_m2c, g.t_m2c_m)
    except PerchError as e:
        raise PerchError(f"ground truth {args.truth}: {e}") from None
    return (g.R_m2c, g.t_m2c_m, gx, gy, gyaw), resting


def _truth_error(truth, b, pts) -> dict:
    """The estimate's errors against the ground truth, printed as one line."""
    R_gt, t_gt, gx, gy, gyaw = truth
    err = {
        "x_m": gx,
        "y_m": gy,
        "yaw_deg": math.degrees(gyaw),
        "adds_m": adi(b.T_m2c[:3, :3], b.T_m2c[:3, 3], R_gt, t_gt, pts),
        "add_m": add(b.T_m2c[:3, :3], b.T_m2c[:3, 3], R_gt, t_gt, pts),
        "xy_error_m": math.hypot(b.x_m - gx, b.y_m - gy),
        "yaw_error_deg": abs(math.degrees((b.yaw_rad - gyaw + math.pi) % (2 * math.pi) - math.pi)),
    }
    print(
        f"truth: x = {gx:+.4f} m, y = {gy:+.4f} m, yaw = {math.degrees(gyaw):.1f} deg; "
        f"ADD-S {err['adds_m'] * 100:.2f} cm, ADD {err['add_m'] * 100:.2f} cm, "
        f"xy error {err['xy_error_m'] * 100:.2f} cm, yaw error {err['yaw_error_deg']:.1f} deg"
    )
    return err


def _write_overlay(path, engine, image, camera, b, truth, out: dict) -> None:
    """The best pose (magenta) over the photo, with the ground truth's outline (green) when known."""
    rgb, mask = engine.render(camera, b.T_m2c)
    pic = overlay_rendering(image, rgb, mask)
    lines = [
        f"estimate (magenta): x {b.x_m:+.3f} m  y {b.y_m:+.3f} m  "
        f"yaw {math.degrees(b.yaw_rad):.0f} deg  score {b.score:.3f}"
    ]
    if truth is not None:
        _, gmask = engine.render(camera, pose_matrix(truth[0], truth[1]))
        pic = overlay_mask(pic, gmask & ~mask, TRUTH_COLOR, tint=0.0)

        pic[mask_contour(gmask)] = TRUTH_COLOR
        lines.append(f"ground truth (green): ADD-S {out['truth']['adds_m'] * 100:.2f} cm")
    save_png(path, caption(pic, lines))


def add_arguments(p: argparse.ArgumentParser) -> None:
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
    g.add_argument(
        "--heatmap",
        default=None,
        help="write a PNG of the best score over yaw at each (x, y) of the searched table: over the photo and "
        "as a top-down map with the best peaks numbered (cells the search did not score are grey)",
    )
    g.add_argument("--quiet", action="store_true", help="no progress bar or notes on stderr")
