"""The main command, `python -m perch_warp IMAGE --mesh MESH --camera CAMERA.json`: estimate one image."""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path
from typing import NamedTuple

from .bop import read_camera_json, truth_instance
from .camera import Camera, camera_from_entry
from .errors import PerchError
from .image import image_header_size, load_rgb, save_png
from .mesh import load_mesh
from .options import (
    add_joint_peaks_argument,
    add_method_arguments,
    add_occluders_argument,
    add_search_arguments,
    build_engine,
    engine_config_from_args,
    resolve_occluders,
    search_space_from_args,
    table_with_extent,
)
from .outputs import check_output_file
from .overlay import TRUTH_COLOR, caption, mask_contour, overlay_mask, overlay_rendering
from .pose_error import add, adi
from .report import conv_line, log, renderer_line, search_summary, timing_line, write_json_atomic
from .resting import DEFAULT_ROLL_STEP_DEG, REST_MODES, Rest, stable_rests, truth_rest, upright_rest
from .table import RestingPose, Table, decompose_on_table, pose_matrix


def image_id_of(args: argparse.Namespace) -> int | None:
    if args.image_id is not None:
        return args.image_id
    m = re.fullmatch(r"0*(\d+)", Path(args.image).stem)
    return int(m.group(1)) if m else None


def run(args: argparse.Namespace) -> int:
    """Entry point of the main command; PerchError propagates to the CLI."""

    # Everything is checked before any work: options, output paths, then the inputs from the cheapest.
    objects = object_list(args)
    resolve_occluders(args, len(objects) > 1, "several objects (--mesh a.obj --mesh b.obj, or --objects ID ID)")
    if len(objects) > 1:
        from .several import run_several  # the several-object command lives in its own module

        return run_several(args, objects)
    args.mesh, obj_id = objects[0].mesh, objects[0].obj_id
    if obj_id is not None and args.obj_id is None:
        args.obj_id = obj_id
    engine_config_from_args(args)
    args.rest = resolve_rest(args)
    check_outputs(args)
    image_id, camera, table = photo_inputs(args)
    truth, truth_resting = read_truth(args, image_id, table)
    mesh = load_mesh(args.mesh, args.mesh_units, untextured=args.untextured)
    space = search_space_from_args(args, camera, table)
    rests = rests_for(args, mesh, truth_resting)
    image = load_photo(args, camera)
    if not args.quiet:
        log(f"mesh: {mesh.source}, units {mesh.units_note}, {len(mesh.faces)} faces")
        log(f"search: {space.describe()}" + extent_note(table))
        log(f"resting poses ({args.rest}): {len(rests)}: " + "; ".join(r.label for r in rests))
    engine = build_engine(args, mesh, args.quiet)
    # One resting pose goes the single-pose way (bit for bit today's search); several, search/rests.py.
    searched = rests[0].pose if len(rests) == 1 else rests
    result = engine.estimate(image, camera, table, searched, space, progress=not args.quiet)
    won = rests[0] if result.resting is None else result.resting.won
    out = {"image": str(args.image), "mesh": str(args.mesh), "rest": args.rest, "resting": won.to_dict()}
    out.update(result.to_dict())
    b = result.best
    print(
        f"pose: x = {b.x_m:+.4f} m, y = {b.y_m:+.4f} m, yaw = {math.degrees(b.yaw_rad):.1f} deg (table frame), "
        f"score {b.score:.4f}"
    )
    print(rest_line(won, len(rests), args.rest))
    print(result.confidence.line())
    print(timing_line(result))
    print(search_summary(result))
    print(renderer_line(result))
    print(conv_line(result))
    if truth is not None:
        out["truth"] = truth_error(truth, b, mesh.vertices_m)
    if args.out:
        write_json_atomic(args.out, out)
    if args.overlay:
        _write_overlay(args.overlay, engine, image, camera, b, truth, out)
    if args.heatmap:
        from .heatmap import write_heatmap  # matplotlib: imported only when a heat map is asked for

        write_heatmap(args.heatmap, image, camera, table, result, None if truth is None else truth[2:4])
    return 0


def photo_inputs(args: argparse.Namespace) -> tuple[int | None, Camera, Table]:
    """The image's id, its camera (checked against the image header's size) and the table frame (with
    --table-extent): everything about the photo but its pixels, read cheaply before any search."""
    width, height = image_header_size(args.image)
    image_id = image_id_of(args)
    entry = camera_entry(args, image_id)
    camera = camera_from_entry(entry, width, height, source=args.camera, image=args.image)
    return image_id, camera, table_with_extent(args, Table.from_entry(entry, source=args.camera))


def load_photo(args: argparse.Namespace, camera: Camera):
    """The image's pixels, refused if the file changed since photo_inputs read its header."""
    image = load_rgb(args.image)
    if image.shape[:2] != (camera.height, camera.width):
        raise PerchError(f"image {args.image} changed while being read")
    return image


class ObjectSpec(NamedTuple):
    """An object to search: its mesh file, a short name, and its BOP id where known (--objects)."""

    mesh: str
    name: str
    obj_id: int | None


def object_list(args: argparse.Namespace) -> list[ObjectSpec]:
    """The objects to search: --mesh (once or more) or --models DIR --objects ID ...; refused in one line
    when neither or both are given, or an id has no mesh."""
    if args.models is not None or args.objects:
        if args.mesh:
            raise PerchError("give either --mesh or --models DIR --objects ID ..., not both")
        if args.models is None or not args.objects:
            raise PerchError("--models DIR and --objects ID ... go together (meshes DIR/obj_000001.obj, ...)")
        if len(set(args.objects)) != len(args.objects):
            raise PerchError(f"--objects lists an id twice: {args.objects}")
        specs = []
        for obj_id in args.objects:
            path = next(
                (p for p in (Path(args.models) / f"obj_{obj_id:06d}{x}" for x in (".obj", ".ply")) if p.is_file()), None
            )
            if path is None:
                raise PerchError(f"--objects {obj_id}: no mesh {Path(args.models) / f'obj_{obj_id:06d}.obj'} (or .ply)")
            specs.append(ObjectSpec(str(path), f"obj {obj_id}", obj_id))
        return specs
    if not args.mesh:
        raise PerchError("no object given: --mesh MESH (once per object) or --models DIR --objects ID ...")
    names = [Path(m).name for m in args.mesh]
    # The same mesh twice (two copies of an object) gets numbered names: every output tells them apart.
    return [
        ObjectSpec(m, f"{name} #{names[:n].count(name) + 1}" if names.count(name) > 1 else name, None)
        for n, (m, name) in enumerate(zip(args.mesh, names, strict=True))
    ]


def check_outputs(args: argparse.Namespace) -> None:
    """The output paths can be written (checked before any work)."""
    if args.out:
        check_output_file(args.out, "--out")
    if args.overlay:
        check_output_file(args.overlay, "--overlay")
    if args.heatmap:
        check_output_file(args.heatmap, "--heatmap")


def extent_note(table: Table) -> str:
    """What the search log adds when the table has an extent."""
    if table.extent_m is None:
        return ""
    return f"; only where the model origin is on the table extent ({len(table.extent_m)} corners)"


def rest_line(won: Rest, n: int, mode: str) -> str:
    """The resting pose of the answer: which face is down (and roll), the model origin's height."""
    how = f"best of {n} {mode} resting poses" if n > 1 else f"--rest {mode}"
    return f"resting: {won.label}, model origin {won.pose.z_m:.4f} m above the table ({how})"


def rests_for(args: argparse.Namespace, mesh, truth_resting: RestingPose | None) -> list[Rest]:
    """The resting poses to search (--rest): the mesh's stable ones, upright, or the ground truth's."""
    lift_m = args.lift_mm / 1000.0
    if args.rest == "truth":
        return [truth_rest(truth_resting)]
    if args.rest == "upright":
        return [upright_rest(mesh.vertices_m, lift_m)]
    return stable_rests(mesh.vertices_m, mesh.faces, args.roll_step, lift_m=lift_m)


def resolve_rest(args: argparse.Namespace, ids_known: bool | None = None) -> str:
    """--rest as given, else truth with --truth (the thesis's protocol, as before) and stable without;
    refused (one line) when truth is asked without a ground truth (ids_known: the objects' ids are
    known; default: --obj-id is given)."""
    rest = args.rest or ("truth" if args.truth else "stable")
    ids_known = args.obj_id is not None if ids_known is None else ids_known
    if rest == "truth" and not (args.truth and ids_known):
        raise PerchError("--rest truth needs --truth scene_gt.json and --obj-id N (the ground truth's resting pose)")
    if not (math.isfinite(args.roll_step) and 0 < args.roll_step <= 360):
        raise PerchError(f"--roll-step must be in (0, 360] degrees, got {args.roll_step}")
    return rest


def camera_entry(args: argparse.Namespace, image_id: int | None) -> dict:
    """The camera entry for the image: by --image-id, else by the image name's number, else the file's only one."""
    try:
        return read_camera_json(args.camera, image_id)
    except PerchError:
        if args.image_id is None and image_id is not None:
            return read_camera_json(args.camera, None)
        raise


def read_truth(args: argparse.Namespace, image_id: int | None, table: Table, obj_id: int | None = None):
    """(R_gt, t_gt, x, y, yaw) and the ground truth's resting pose from --truth and --obj-id (or `obj_id`),
    or (None, None)."""
    obj_id = args.obj_id if obj_id is None else obj_id
    if not (args.truth or obj_id is not None):
        return None, None
    if not args.truth:
        raise PerchError("--obj-id needs --truth (a BOP scene_gt.json)")
    g = truth_instance(args.truth, args.image_id if args.image_id is not None else image_id, obj_id)
    try:
        resting, gx, gy, gyaw = decompose_on_table(table, g.R_m2c, g.t_m2c_m)
    except PerchError as e:
        raise PerchError(f"ground truth {args.truth}: {e}") from None
    return (g.R_m2c, g.t_m2c_m, gx, gy, gyaw), resting


def truth_error(truth, b, pts) -> dict:
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
        f"yaw {math.degrees(b.yaw_rad):.0f} deg  score {b.score:.3f}",
        f"resting: {out['resting']['label']}, {out['resting']['z_m']:.3f} m high",
    ]
    if truth is not None:
        _, gmask = engine.render(camera, pose_matrix(truth[0], truth[1]))
        pic = overlay_mask(pic, gmask & ~mask, TRUTH_COLOR, tint=0.0)

        pic[mask_contour(gmask)] = TRUTH_COLOR
        lines.append(f"ground truth (green): ADD-S {out['truth']['adds_m'] * 100:.2f} cm")
    save_png(path, caption(pic, lines))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("image", help="RGB photo (PNG/JPEG)")
    _add_object_arguments(p)
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
    _add_table_arguments(p)
    p.add_argument(
        "--truth",
        default=None,
        help="BOP scene_gt.json: report the estimate's error against the ground truth of --obj-id, and "
        "(unless --rest says otherwise) take height, roll and pitch from it (thesis protocol)",
    )
    p.add_argument("--obj-id", type=int, default=None, help="object id in --truth")
    p.add_argument(
        "--rest",
        choices=REST_MODES,
        default=None,
        help="how the object rests: stable (every stable pose of the mesh, searched together; about as many "
        "times the cost), upright (model +z up), truth (from --truth; the thesis's protocol). "
        "Default: truth with --truth, else stable",
    )
    p.add_argument(
        "--roll-step",
        type=float,
        default=DEFAULT_ROLL_STEP_DEG,
        help=f"--rest stable: roll step (deg) about the axis of an object lying on a curved side, e.g. a can "
        f"(default: {DEFAULT_ROLL_STEP_DEG:g})",
    )
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


def _add_object_arguments(p: argparse.ArgumentParser) -> None:
    """What to find: one mesh, or several (the joint step)."""
    p.add_argument(
        "--mesh",
        action="append",
        default=None,
        help="object mesh: textured OBJ, PLY with vertex colours, PLY/GLB with UVs; once per object to find "
        "several objects in the photo (each object's search, then the joint step)",
    )
    p.add_argument(
        "--models", default=None, metavar="DIR", help="meshes folder (BOP: DIR/obj_000001.obj), with --objects"
    )
    p.add_argument(
        "--objects",
        type=int,
        nargs="+",
        default=None,
        metavar="ID",
        help="object ids to find in --models (several: the joint step; with --truth, their ground truths)",
    )
    add_joint_peaks_argument(p, "several objects")
    add_occluders_argument(p, "several objects")


def _add_table_arguments(p: argparse.ArgumentParser) -> None:
    """Where the table top is and what the object stands on."""
    p.add_argument(
        "--table-extent",
        type=float,
        nargs=4,
        default=None,
        metavar=("X0", "X1", "Y0", "Y1"),
        help="the table top is this rectangle of the table frame (metres): poses whose model origin lies "
        "outside are never scored (default: the camera file's table_extent_mm polygon, else the whole plane)",
    )
    p.add_argument(
        "--lift-mm", type=float, default=0.0, help="the surface the object stands on is this high above the table (mm)"
    )
