"""`python -m perch_warp demo`: the whole pipeline, offline, on a scene the project makes itself.

A procedurally textured box stands on a procedurally textured table among distractors;
the photo is taken by `photograph` (shading, shadows, colour cast, blur, noise), not by
the engine's flat renderer, so recovering the pose is a real test. The demo writes the
scene as files the CLI reads (photo, BOP camera/ground truth, OBJ), estimates the pose,
prints it against the truth and writes an overlay.
"""

from __future__ import annotations

import argparse
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import bop
from .camera import Camera
from .errors import PerchError
from .image import save_png
from .mesh import ObjectMesh
from .options import add_method_arguments, build_engine
from .overlay import TRUTH_COLOR, caption, mask_contour, overlay_rendering
from .pose_error import adi
from .report import conv_line, log, renderer_line, search_summary, timing_line, write_json_atomic
from .resting import down_to_table
from .scene import (
    label_texture,
    look_at_table,
    quad,
    striped_cylinder,
    textured_box,
    wall_texture,
    wood_texture,
    write_obj,
)
from .search_space import SearchSpace
from .table import RestingPose, Table, model_to_camera, pose_matrix

# --- the demo scene -------------------------------------------------------------------------


@dataclass
class DemoScene:
    image: np.ndarray
    camera: Camera
    table: Table
    mesh: ObjectMesh
    resting: RestingPose
    truth_xy_yaw: tuple[float, float, float]
    space: SearchSpace
    label: np.ndarray


def demo_scene(
    seed: int = 0,
    width: int = 320,
    height: int = 240,
    xy_step_m: float = 0.01,
    yaw_step_deg: float = 15.0,
    half_range_m: float = 0.1,
    device: str = "cpu",
    target_down: np.ndarray | None = None,
) -> DemoScene:
    """The demo's scene: box target at a random (x, y, yaw), two distractors, and a search square
    centred on the table origin (where the camera looks), not on the target. `target_down` (model
    frame): the box lies on the face whose outward normal this is (default: upright, model -z down)."""
    # Imported here: photo.py imports Warp (seconds), which `demo --help` does not need.
    from .photo import Placed, photograph

    rng = np.random.default_rng(seed)
    f = 0.95 * width
    camera = Camera(np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]), width, height)
    table = look_at_table(0.6, 50.0, float(rng.uniform(-25, 25)))
    target = textured_box((0.11, 0.075, 0.05), label_texture(rng), "demo box")
    R_rest = None if target_down is None else down_to_table(target_down)
    resting = RestingPose.upright(target.vertices_m, R_rest)
    gx, gy = rng.uniform(-0.06, 0.06, 2)
    gyaw = float(rng.uniform(0, 2 * math.pi))
    scene = []

    def place(mesh: ObjectMesh, x: float, y: float, yaw: float, rp: RestingPose | None = None) -> None:
        rp = rp or RestingPose.upright(mesh.vertices_m)
        R, t = model_to_camera(table, rp, x, y, yaw)
        scene.append(Placed(mesh, R[0], t[0]))

    place(target, gx, gy, gyaw, resting)
    # Distractors on the far side, so they occlude little but compete in appearance.
    place(textured_box((0.07, 0.07, 0.12), label_texture(rng), "distractor box"), gx - 0.15, gy + 0.12, 0.6)
    place(striped_cylinder(0.035, 0.11, rng), gx + 0.14, gy + 0.13, 0.0)
    s = 0.8
    table_corners = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]])
    scene.append(Placed(quad(table_corners, wood_texture(rng), repeat=3.0, name="table"), table.R_t2c, table.t_t2c_m))
    wall = np.array([[-s, 0.7, 0], [s, 0.7, 0], [s, 0.7, 0.8], [-s, 0.7, 0.8]])
    scene.append(Placed(quad(wall, wall_texture(rng), repeat=2.0, name="wall"), table.R_t2c, table.t_t2c_m))
    light_c = table.to_camera(np.array([0.35, -0.25, 0.9]))
    image, label = photograph(scene, camera, light_c, rng, device=device)
    space = SearchSpace(
        (-half_range_m, half_range_m),
        (-half_range_m, half_range_m),
        xy_step_m,
        (0.0, 2 * math.pi),
        math.radians(yaw_step_deg),
    )
    return DemoScene(image, camera, table, target, resting, (float(gx), float(gy), gyaw), space, label)


def write_scene(sc: DemoScene, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The scene as files the CLI reads: rgb/000001.png, models/obj_000001.obj, BOP scene_camera.json
    and scene_gt.json (mm). Returns the true model -> camera pose (R, t in metres)."""
    (folder / "models").mkdir(parents=True, exist_ok=True)
    (folder / "rgb").mkdir(exist_ok=True)
    gx, gy, gyaw = sc.truth_xy_yaw
    R_gt, t_gt = (a[0] for a in model_to_camera(sc.table, sc.resting, gx, gy, gyaw))
    save_png(folder / "rgb" / "000001.png", sc.image)
    write_obj(sc.mesh, folder / "models" / "obj_000001.obj")
    cam_entry = {
        "cam_K": sc.camera.K.reshape(-1).tolist(),
        "cam_R_w2c": sc.table.R_t2c.reshape(-1).tolist(),
        "cam_t_w2c": (sc.table.t_t2c_m * 1000).tolist(),
        "depth_scale": 1.0,
    }
    gt_entry = {"obj_id": 1, "cam_R_m2c": R_gt.reshape(-1).tolist(), "cam_t_m2c": (t_gt * 1000).tolist()}
    bop.write_scene(folder, {1: cam_entry}, {1: [gt_entry]})
    return R_gt, t_gt


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="perch_warp_demo", help="output folder (default: ./perch_warp_demo)")
    p.add_argument("--scene-seed", type=int, default=0, help="which random scene (default: 0)")
    p.add_argument("--yaw-step", type=float, default=15.0, help="yaw step in degrees (default: 15)")
    add_method_arguments(p)


def _overlay(engine, sc: DemoScene, result, T_gt: np.ndarray, adds: float) -> np.ndarray:
    """The photo with the estimate's rendering (magenta) and the truth's outline (green), captioned."""
    b = result.best
    gx, gy, gyaw = sc.truth_xy_yaw
    rgb, mask = engine.render(sc.camera, b.T_m2c)
    _, gmask = engine.render(sc.camera, T_gt)
    pic = overlay_rendering(sc.image, rgb, mask)
    pic[mask_contour(gmask, 1)] = TRUTH_COLOR
    return caption(
        pic,
        [
            f"estimate (magenta) x {b.x_m:+.3f} y {b.y_m:+.3f} m yaw {math.degrees(b.yaw_rad):.0f} deg",
            f"truth (green)    x {gx:+.3f} y {gy:+.3f} m yaw {math.degrees(gyaw) % 360:.0f} deg",
            f"ADD-S {adds * 100:.2f} cm, search {result.timings_s['total']:.1f} s on {result.device}",
        ],
    )


def _print_outcome(args: argparse.Namespace, sc: DemoScene, result, adds: float, yaw_err: float, out: Path) -> bool:
    """Print the estimate against the truth and what the search did; True when within one grid step."""
    b = result.best
    gx, gy, gyaw = sc.truth_xy_yaw
    step = sc.space.xy_step_m
    ok = math.hypot(b.x_m - gx, b.y_m - gy) <= step * math.sqrt(2) + 1e-9 and yaw_err <= args.yaw_step + 1e-9
    print(f"truth:    x = {gx:+.4f} m, y = {gy:+.4f} m, yaw = {math.degrees(gyaw) % 360:6.1f} deg")
    print(
        f"estimate: x = {b.x_m:+.4f} m, y = {b.y_m:+.4f} m, yaw = {math.degrees(b.yaw_rad):6.1f} deg, "
        f"score {b.score:.3f}"
    )
    print(result.confidence.line())
    ref = result.info.extra.get("refine")
    print(
        f"error: ADD-S {adds * 100:.2f} cm, yaw {yaw_err:.1f} deg -> {'within' if ok else 'NOT within'} one grid step"
        + (
            f" ({step * 100:g} cm, {args.yaw_step:g} deg; refined below it at {ref['step_xy_m'] * 1000:.3g} mm, "
            f"{ref['step_yaw_deg']:.3g} deg steps)"
            if ref
            else ""
        )
    )
    print(timing_line(result))
    print(search_summary(result))
    print(renderer_line(result))
    print(conv_line(result))
    print(f"wrote {out}/overlay.png, {out}/result.json and the scene files; rerun the search with:")
    print(
        f"  python -m perch_warp {out}/rgb/000001.png --mesh {out}/models/obj_000001.obj "
        f"--camera {out}/scene_camera.json --x-range -0.1 0.1 --y-range -0.1 0.1 --yaw-step {args.yaw_step:g} "
        f"--rest upright --overlay {out}/overlay_cli.png --heatmap {out}/heatmap.png"
    )
    return ok


def run(args: argparse.Namespace) -> int:
    """Entry point of `python -m perch_warp demo`; exit 3 when the estimate is off by more than a grid step."""
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise PerchError(f"--out {out} exists and is not a folder")
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)

    try:
        log("demo: photographing a procedural scene (shading, shadows, noise; not the engine's renderer)...")
        t0 = time.perf_counter()
        sc = demo_scene(seed=args.scene_seed, yaw_step_deg=args.yaw_step, device=args.device or "cpu")
        gx, gy, gyaw = sc.truth_xy_yaw
        R_gt, t_gt = write_scene(sc, tmp)
        log(f"demo: scene ready in {time.perf_counter() - t0:.1f} s; search {sc.space.describe()}")

        engine = build_engine(args, sc.mesh)
        result = engine.estimate(sc.image, sc.camera, sc.table, sc.resting, sc.space, progress=True)
        b = result.best
        adds = adi(b.T_m2c[:3, :3], b.T_m2c[:3, 3], R_gt, t_gt, sc.mesh.vertices_m)
        yaw_err = abs(math.degrees((b.yaw_rad - gyaw + math.pi) % (2 * math.pi) - math.pi))
        save_png(tmp / "overlay.png", _overlay(engine, sc, result, pose_matrix(R_gt, t_gt), adds))
        write_json_atomic(
            tmp / "result.json",
            {**result.to_dict(), "truth": {"x_m": gx, "y_m": gy, "yaw_deg": math.degrees(gyaw), "adds_m": adds}},
        )
        shutil.rmtree(out, ignore_errors=True)
        tmp.rename(out)

    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # leave nothing half-written
        raise

    ok = _print_outcome(args, sc, result, adds, yaw_err, out)
    return 0 if ok else 3
