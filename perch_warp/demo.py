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
from .mesh import ObjectMesh
from .options import add_method_arguments, build_engine
from .report import conv_line, log, renderer_line, search_summary, timing_line, write_json_atomic
from .resting import down_to_table
from .search_space import SearchSpace
from .table import RestingPose, Table, model_to_camera

# --- procedural textures (float RGB in [0, 1], row 0 = texture v 0) -------------------------------


def _noise(rng: np.random.Generator, h: int, w: int, scale: int) -> np.ndarray:
    """Smooth value noise: a coarse random grid, bilinearly upsampled."""
    g = rng.random((h // scale + 2, w // scale + 2))
    y = np.arange(h) / scale
    x = np.arange(w) / scale
    y0, x0 = y.astype(int), x.astype(int)
    fy, fx = (y - y0)[:, None], (x - x0)[None, :]
    a, b = g[y0][:, x0], g[y0][:, x0 + 1]
    c, d = g[y0 + 1][:, x0], g[y0 + 1][:, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def wood_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size] / size
    rings = np.sin(2 * np.pi * (xx * 9 + 1.5 * _noise(rng, size, size, 64))) * 0.5 + 0.5
    grain = _noise(rng, size, size, 4)
    t = 0.6 * rings + 0.4 * grain
    base, dark = np.array([0.72, 0.55, 0.36]), np.array([0.45, 0.30, 0.17])
    return (base * t[..., None] + dark * (1 - t[..., None])).astype(np.float32)


def wall_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    n = _noise(rng, size, size, 16)[..., None]
    return (np.array([0.80, 0.82, 0.86]) * (0.85 + 0.15 * n)).astype(np.float32)


def label_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A 3 x 2 atlas of distinct, colourful faces (stripes, checks, discs, blocks)."""
    tex = np.zeros((size, size, 3), np.float32)
    th, tw = size // 2, size // 3
    palette = rng.random((12, 3)) * 0.8 + 0.1
    yy, xx = np.mgrid[0:th, 0:tw]
    for k in range(6):
        r, c = divmod(k, 3)
        a, b = palette[2 * k], palette[2 * k + 1]
        kind = k % 4
        if kind == 0:
            m = ((xx + yy) // 12) % 2 == 0
        elif kind == 1:
            m = ((xx // 16) + (yy // 16)) % 2 == 0
        elif kind == 2:
            m = (xx - tw / 2) ** 2 + (yy - th / 2) ** 2 < (min(th, tw) / 3) ** 2
        else:
            m = (yy // 20) % 3 == 0
        tile = np.where(m[..., None], a, b)
        # A few random blocks make every face's appearance asymmetric.
        for _ in range(3):
            y0, x0 = rng.integers(0, th - 30), rng.integers(0, tw - 30)
            tile[y0 : y0 + 24, x0 : x0 + 24] = rng.random(3)
        tex[r * th : (r + 1) * th, c * tw : (c + 1) * tw] = tile
    return tex


# --- procedural meshes (model frame, metres) --------------------------------------------------


def textured_box(size_m: tuple[float, float, float], texture: np.ndarray, name: str = "box") -> ObjectMesh:
    """A box centred on the origin, each face mapped to one tile of a 3 x 2 texture atlas."""
    sx, sy, sz = (s / 2 for s in size_m)
    faces_def = [  # outward normal axis, sign, and the two in-plane axes (u, v)
        (0, +1, 1, 2),
        (0, -1, 1, 2),
        (1, +1, 0, 2),
        (1, -1, 0, 2),
        (2, +1, 0, 1),
        (2, -1, 0, 1),
    ]
    half = np.array([sx, sy, sz])
    V, UV, F = [], [], []
    for k, (ax, sign, ua, va) in enumerate(faces_def):
        r, c = divmod(k, 3)
        corners = []
        for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            p = np.zeros(3)
            p[ax] = sign * half[ax]
            p[ua] = du * half[ua]
            p[va] = dv * half[va]
            corners.append(p)
            UV.append(((c + (du + 1) / 2 * 0.96 + 0.02) / 3, (r + (dv + 1) / 2 * 0.96 + 0.02) / 2))
        n0 = len(V)
        V.extend(corners)
        # Wind each quad so that its normal points outwards.
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        if normal[ax] * sign > 0:
            F += [(n0, n0 + 1, n0 + 2), (n0, n0 + 2, n0 + 3)]
        else:
            F += [(n0, n0 + 2, n0 + 1), (n0, n0 + 3, n0 + 2)]
    return ObjectMesh(
        np.array(V),
        np.array(F, np.int32),
        np.array(UV, np.float32),
        np.ascontiguousarray(texture[::-1]),
        None,
        name,
        "m (procedural)",
    )


def striped_cylinder(radius_m: float, height_m: float, rng: np.random.Generator, sections: int = 48) -> ObjectMesh:
    import trimesh

    m = trimesh.creation.cylinder(radius=radius_m, height=height_m, sections=sections)
    V = np.asarray(m.vertices)
    band = ((V[:, 2] + height_m / 2) / height_m * 5).astype(int) % 2
    colors = np.where(band[:, None] == 1, rng.random(3) * 0.7 + 0.2, rng.random(3) * 0.7 + 0.2).astype(np.float32)
    return ObjectMesh(V, np.asarray(m.faces, np.int32), None, None, colors, "cylinder", "m (procedural)")


def quad(corners_m: np.ndarray, texture: np.ndarray, repeat: float = 1.0, name: str = "quad") -> ObjectMesh:
    uv = np.array([[0, 0], [repeat, 0], [repeat, repeat], [0, repeat]], np.float32)
    return ObjectMesh(
        np.asarray(corners_m, float), np.array([[0, 1, 2], [0, 2, 3]], np.int32), uv, texture, None, name, "m"
    )


# --- the photographer -------------------------------------------------------------------------


@dataclass
class Placed:
    mesh: ObjectMesh
    R_m2c: np.ndarray
    t_m2c_m: np.ndarray


def photograph(
    scene: list[Placed],
    camera: Camera,
    light_c_m: np.ndarray,
    rng: np.random.Generator,
    device: str = "cpu",
    noise_sigma: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A lit, shadowed, noisy uint8 photo of the scene, and the per-pixel index of the visible mesh (-1: none)."""
    import warp as wp

    from .kernels.photo import primary_pass, shadow_pass

    wp.config.log_level = wp.LOG_WARNING
    H, W = camera.height, camera.width
    with wp.ScopedDevice(device):
        depth = wp.full((H, W), 1.0e6, dtype=float)
        albedo = wp.zeros((H, W), dtype=wp.vec3)
        normal = wp.zeros((H, W), dtype=wp.vec3)
        label = wp.full((H, W), -1, dtype=wp.int32)
        lit = wp.ones((H, W), dtype=float)
        meshes = []
        for k, item in enumerate(scene):
            m = item.mesh
            Vc = (m.vertices_m @ np.asarray(item.R_m2c).T + item.t_m2c_m).astype(np.float32)
            pts = wp.array(Vc, dtype=wp.vec3)
            idx = wp.array(m.faces.reshape(-1).astype(np.int32), dtype=wp.int32)
            wm = wp.Mesh(points=pts, indices=idx)
            meshes.append((wm, pts, idx))
            tex = m.texture is not None
            wp.launch(
                primary_pass,
                dim=(H, W),
                inputs=[
                    wm.id,
                    idx,
                    wp.array(m.uv if tex else np.zeros((1, 2), np.float32), dtype=wp.vec2),
                    wp.array(m.texture if tex else np.zeros((1, 1, 3), np.float32), dtype=wp.vec3),
                    wp.array(m.vertex_colors if not tex else np.zeros((1, 3), np.float32), dtype=wp.vec3),
                    int(tex),
                    camera.fx,
                    camera.fy,
                    camera.cx,
                    camera.cy,
                ],
                outputs=[depth, albedo, normal, label, k],
            )
        light = wp.vec3(*np.asarray(light_c_m, np.float32).tolist())
        for wm, _, _ in meshes:
            wp.launch(
                shadow_pass,
                dim=(H, W),
                inputs=[wm.id, camera.fx, camera.fy, camera.cx, camera.cy, light, depth, normal],
                outputs=[lit],
            )
        d, a, n, lab, s = depth.numpy(), albedo.numpy(), normal.numpy(), label.numpy(), lit.numpy()
    # Shading on the host: Lambert + Blinn-Phong highlight, ambient fill, warm colour cast, gamma.
    vv, uu = np.mgrid[0:H, 0:W]
    dirs = np.stack([(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, np.ones_like(uu, float)], -1)
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    P = dirs * np.where(lab >= 0, d, 0)[..., None]
    L = light_c_m - P
    L /= np.linalg.norm(L, axis=-1, keepdims=True)
    ndl = np.clip((n * L).sum(-1), 0, None)
    Hh = L - dirs
    Hh /= np.linalg.norm(Hh, axis=-1, keepdims=True) + 1e-9
    spec = np.clip((n * Hh).sum(-1), 0, None) ** 40
    shade = 0.38 + 0.78 * ndl * s
    img = a * shade[..., None] + 0.12 * (spec * s)[..., None]
    bg = np.array([0.55, 0.6, 0.68]) * (0.8 + 0.2 * (vv / H))[..., None]
    img = np.where((lab >= 0)[..., None], img, bg)
    img = np.clip(img * np.array([1.06, 1.0, 0.9]), 0, 1) ** (1 / 1.1)
    # Optics blur (3x3 binomial) and sensor noise.
    k = np.array([1.0, 2.0, 1.0]) / 4
    img = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 0, img)
    img = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 1, img)
    img = img * 255 + rng.normal(0, noise_sigma, img.shape)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), lab


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


def look_at_table(distance_m: float, elevation_deg: float, azimuth_deg: float) -> Table:
    """A camera `distance_m` from the table origin, `elevation_deg` above the table, looking at the origin."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    C = distance_m * np.array([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), math.sin(el)])
    z = -C / np.linalg.norm(C)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Table(R, -R @ C)


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


def write_obj(mesh: ObjectMesh, path: Path) -> None:
    """The mesh as a textured OBJ (+ .mtl + .png), in metres."""
    from .image import save_png

    png = path.with_suffix(".png")
    save_png(png, (np.clip(mesh.texture[::-1], 0, 1) * 255 + 0.5).astype(np.uint8))
    path.with_suffix(".mtl").write_text(f"newmtl material_0\nKd 1 1 1\nmap_Kd {png.name}\n")
    lines = [f"mtllib {path.with_suffix('.mtl').name}", "usemtl material_0"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices_m]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in mesh.uv]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")


def write_scene(sc: DemoScene, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The scene as files the CLI reads: rgb/000001.png, models/obj_000001.obj, BOP scene_camera.json
    and scene_gt.json (mm). Returns the true model -> camera pose (R, t in metres)."""
    from .image import save_png

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


def run(args: argparse.Namespace) -> int:
    from .image import save_png
    from .overlay import TRUTH_COLOR, caption, mask_contour, overlay_rendering
    from .pose_error import adi
    from .table import pose_matrix

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
        rgb, mask = engine.render(sc.camera, b.T_m2c)
        _, gmask = engine.render(sc.camera, pose_matrix(R_gt, t_gt))
        pic = overlay_rendering(sc.image, rgb, mask)
        pic[mask_contour(gmask, 1)] = TRUTH_COLOR
        pic = caption(
            pic,
            [
                f"estimate (magenta) x {b.x_m:+.3f} y {b.y_m:+.3f} m yaw {math.degrees(b.yaw_rad):.0f} deg",
                f"truth (green)    x {gx:+.3f} y {gy:+.3f} m yaw {math.degrees(gyaw) % 360:.0f} deg",
                f"ADD-S {adds * 100:.2f} cm, search {result.timings_s['total']:.1f} s on {result.device}",
            ],
        )
        save_png(tmp / "overlay.png", pic)
        write_json_atomic(
            tmp / "result.json",
            {**result.to_dict(), "truth": {"x_m": gx, "y_m": gy, "yaw_deg": math.degrees(gyaw), "adds_m": adds}},
        )
        shutil.rmtree(out, ignore_errors=True)
        tmp.rename(out)

    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # leave nothing half-written
        raise

    step = sc.space.xy_step_m
    ok = math.hypot(b.x_m - gx, b.y_m - gy) <= step * math.sqrt(2) + 1e-9 and yaw_err <= args.yaw_step + 1e-9
    print(f"truth:    x = {gx:+.4f} m, y = {gy:+.4f} m, yaw = {math.degrees(gyaw) % 360:6.1f} deg")
    print(
        f"estimate: x = {b.x_m:+.4f} m, y = {b.y_m:+.4f} m, yaw = {math.degrees(b.yaw_rad):6.1f} deg, "
        f"score {b.score:.3f}"
    )
    print(result.confidence.line())
    ref = result.info.get("refine")
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
        f"--overlay {out}/overlay_cli.png --heatmap {out}/heatmap.png"
    )
    return 0 if ok else 3
