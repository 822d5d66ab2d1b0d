"""Scene building shared by the demo (perch_warp.demo: its offline photo) and the synthetic sets
(perch_warp.synth: Mitsuba scenes): procedural noise and textures, procedural meshes, camera
placement, and writing meshes and images as BOP datasets hold them.

Frames and units: meshes in their model frame, metres; the table frame has z up with z = 0 the
table top; cameras are OpenCV (x right, y down, z forward). Textures are float RGB in [0, 1] with
row 0 at texture v = 0. The demo's and the synthetic sets' textures are different procedures
(value noise vs. spline noise) whose outputs the demo's results and the published synthetic sets
depend on, so both are kept, each under its own name.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image
from scipy.ndimage import zoom

from .image import save_png
from .mesh import ObjectMesh
from .table import Table

# --- procedural textures (float RGB in [0, 1], row 0 = texture v 0) -------------------------------


def value_noise(rng: np.random.Generator, h: int, w: int, scale: int) -> np.ndarray:
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
    rings = np.sin(2 * np.pi * (xx * 9 + 1.5 * value_noise(rng, size, size, 64))) * 0.5 + 0.5
    grain = value_noise(rng, size, size, 4)
    t = 0.6 * rings + 0.4 * grain
    base, dark = np.array([0.72, 0.55, 0.36]), np.array([0.45, 0.30, 0.17])
    return (base * t[..., None] + dark * (1 - t[..., None])).astype(np.float32)


def wall_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    n = value_noise(rng, size, size, 16)[..., None]
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
    """A closed cylinder (model frame, metres, axis z) in five bands of two random vertex colours."""
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


# --- camera placement (table frame, metres) ---------------------------------------------------


def footprints_separated(a: np.ndarray, b: np.ndarray, margin: float) -> bool:
    """Separating-axis test for convex polygons: True when some edge normal shows a gap > margin."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([edges[:, 1], -edges[:, 0]], 1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
        pa, pb = a @ normals.T, b @ normals.T
        gap = np.maximum(pb.min(0) - pa.max(0), pa.min(0) - pb.max(0))
        if np.any(gap > margin):
            return True
    return False


def look_at_camera(center: np.ndarray, target: np.ndarray, roll: float) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV camera (x right, y down, z forward) at ``center`` looking at ``target``: (R_w2c, t_w2c)."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    R_w2c = np.stack([x, y, z], 0)
    return R_w2c, -R_w2c @ center


def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    pc = pts @ R.T + t
    return np.stack([K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], 1)


def look_at_table(distance_m: float, elevation_deg: float, azimuth_deg: float) -> Table:
    """A camera `distance_m` from the table origin, `elevation_deg` above the table, looking at the origin."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    C = distance_m * np.array([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), math.sin(el)])
    return Table(*look_at_camera(C, np.zeros(3), 0.0))


# --- procedural textures of the synthetic sets (linear RGB in [0, 1]) ----------------------


def spline_noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float]) -> np.ndarray:
    """Smooth value noise in [-1, 1]-ish: a coarse Gaussian grid upsampled with cubic splines."""
    gh, gw = max(2, int(cells[0])), max(2, int(cells[1]))
    g = rng.standard_normal((gh + 3, gw + 3))
    fy, fx = shape[0] / gh, shape[1] / gw
    up = zoom(g, (fy, fx), order=3)  # (gh + 3) * fy >= shape[0] + 3 rows: crop off the edge effects
    oy, ox = int(fy), int(fx)
    return up[oy : oy + shape[0], ox : ox + shape[1]] / 1.5


def fractal_noise(
    rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float], octaves: int = 4
) -> np.ndarray:
    # Sum the octaves at a quarter of the resolution and upsample linearly: these fields are smooth,
    # and full-resolution cubic upsampling of every octave cost seconds per table texture.
    small = (-(-shape[0] // 4), -(-shape[1] // 4))
    out = np.zeros(small)
    amp = 1.0
    for o in range(octaves):
        out += amp * spline_noise(rng, small, (cells[0] * 2**o, cells[1] * 2**o))
        amp *= 0.5
    return zoom(out, 4, order=1)[: shape[0], : shape[1]]


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def planked_wood_texture(rng: np.random.Generator, h: int, w: int, size_m: tuple[float, float]) -> np.ndarray:
    """Planked wood: grain along x, per-plank ring offsets and tint, dark seams; linear RGB."""
    palettes = [
        ((0.78, 0.60, 0.40), (0.55, 0.36, 0.20)),
        ((0.45, 0.30, 0.19), (0.26, 0.16, 0.09)),
        ((0.88, 0.76, 0.58), (0.70, 0.55, 0.37)),
        ((0.62, 0.42, 0.27), (0.40, 0.24, 0.13)),
    ]
    light, dark = (srgb_to_linear(np.array(c)) for c in palettes[rng.integers(len(palettes))])
    ys = (np.arange(h, dtype=np.float32)[:, None] / h * size_m[1]).astype(np.float32)
    xs = (np.arange(w, dtype=np.float32)[None, :] / w * size_m[0]).astype(np.float32)
    plank_w = rng.uniform(0.09, 0.2)
    plank = np.floor(ys / plank_w).astype(int)  # (h, 1): planks run along x
    n_planks = int(plank.max()) + 1
    offs = rng.uniform(0, 50, n_planks).astype(np.float32)[plank]
    tint = rng.uniform(0.9, 1.1, n_planks).astype(np.float32)[plank]
    warp = fractal_noise(rng, (h, w), (6, 3), 3).astype(np.float32)
    ring_freq = np.float32(rng.uniform(25, 60))  # rings per metre across the grain
    rings = (ys * ring_freq + offs + 1.5 * warp + 0.15 * xs) % 1.0
    a = np.clip(np.abs(rings - 0.5) * 2, 0, 1)
    profile = a * a * np.sqrt(a)
    fibres = spline_noise(rng, (h, w), (h / 3, w / 80)).astype(np.float32)  # stretched along the grain
    t = np.clip(0.55 * profile + 0.12 * fibres + 0.15 * fractal_noise(rng, (h, w), (4, 4), 3) + 0.2, 0, 1)
    t = t.astype(np.float32)[..., None]
    rgb = (light * (1 - t) + dark * t) * tint[..., None]
    seam = ((ys % plank_w) < 0.0012)[:, 0]
    rgb[seam] *= 0.45
    return np.clip(rgb, 0, 1)


def laminate_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    base = np.array([[0.85, 0.85, 0.83], [0.62, 0.63, 0.62], [0.35, 0.36, 0.38], [0.80, 0.74, 0.64]])[rng.integers(4)]
    mottle = 0.04 * fractal_noise(rng, (h, w), (8, 8), 4)
    speck = (rng.random((h, w)) < 0.02) * rng.uniform(-0.25, 0.1, (h, w))
    rgb = base[None, None] * (1 + mottle + speck)[..., None]
    return np.clip(srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


def cloth_texture(rng: np.random.Generator, h: int, w: int, size_m: tuple[float, float]) -> np.ndarray:
    base = np.array([[0.55, 0.12, 0.12], [0.20, 0.30, 0.50], [0.75, 0.72, 0.62], [0.25, 0.40, 0.28]])[rng.integers(4)]
    ys = np.arange(h)[:, None] / h * size_m[1]
    xs = np.arange(w)[None, :] / w * size_m[0]
    weave = 0.5 + 0.5 * np.sin(2 * np.pi * xs / 0.004) * np.sin(2 * np.pi * ys / 0.004)
    check = ((np.floor(xs / 0.06) + np.floor(ys / 0.06)) % 2) if rng.random() < 0.5 else np.zeros_like(xs + ys)
    shade = 0.88 + 0.06 * weave + 0.06 * fractal_noise(rng, (h, w), (10, 10), 3) - 0.25 * check
    rgb = base[None, None] * shade[..., None]
    return np.clip(srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


def plaster_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    base = np.array([[0.80, 0.78, 0.72], [0.70, 0.75, 0.78], [0.85, 0.82, 0.78], [0.60, 0.62, 0.58]])[rng.integers(4)]
    rgb = base[None, None] * (1 + 0.05 * fractal_noise(rng, (h, w), (6, 6), 4))[..., None]
    return np.clip(srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


def floor_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Large square tiles with grout lines and mottling (the floor is 6 m wide)."""
    base = np.array([[0.45, 0.42, 0.38], [0.30, 0.30, 0.32], [0.60, 0.55, 0.48]])[rng.integers(3)]
    ys, xs = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None] * 6.0
    grout = ((xs % 0.5) < 0.006) | ((ys % 0.5) < 0.006)
    rgb = base[None, None] * (1 + 0.08 * fractal_noise(rng, (h, w), (12, 12), 3))[..., None]
    rgb[grout] *= 0.6
    return np.clip(srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


def environment_map(rng: np.random.Generator, harsh: bool, h: int = 128, w: int = 256) -> np.ndarray:
    """Equirectangular indoor panorama (rows: +y_env at the top): ceiling, walls, floor, windows, lamps."""
    theta = (np.arange(h) + 0.5) / h * np.pi  # 0 = up
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    elev = np.pi / 2 - theta[:, None] + 0 * phi[None, :]
    warm = np.array([1.0, 0.93, 0.84]) if rng.random() < 0.5 else np.array([0.92, 0.96, 1.0])
    ceiling = 0.9 * warm
    wall = rng.uniform(0.25, 0.5) * np.array([1.0, 0.97, 0.92])
    floor = np.array([0.12, 0.11, 0.10])
    env = np.where(elev[..., None] > 0.6, ceiling, np.where(elev[..., None] > -0.05, wall, floor))
    env = env * (1 + 0.15 * fractal_noise(rng, (h, w), (4, 8), 3))[..., None]
    n_windows = 0 if harsh else int(rng.integers(1, 3))
    for _ in range(n_windows):
        c_phi = rng.uniform(0, 2 * np.pi)
        d_phi = np.abs((phi[None, :] - c_phi + np.pi) % (2 * np.pi) - np.pi)
        win = (d_phi < rng.uniform(0.25, 0.5)) & (elev > rng.uniform(0.05, 0.2)) & (elev < rng.uniform(0.6, 0.9))
        env[win] = rng.uniform(4, 9) * np.array([0.95, 0.98, 1.05])
    for _ in range(int(rng.integers(1, 4))):  # ceiling lamps
        c_phi, c_el = rng.uniform(0, 2 * np.pi), rng.uniform(0.9, 1.4)
        d = np.hypot(((phi[None, :] - c_phi + np.pi) % (2 * np.pi) - np.pi) * np.cos(elev), elev - c_el)
        env[d < 0.08] = rng.uniform(8, 20) * warm
    return np.maximum(env, 0).astype(np.float32)


# --- writing (BOP layout) ---------------------------------------------------------------------


def write_obj(mesh: ObjectMesh, path: Path) -> None:
    """The mesh as a textured OBJ (+ .mtl + .png), in metres."""
    png = path.with_suffix(".png")
    save_png(png, (np.clip(mesh.texture[::-1], 0, 1) * 255 + 0.5).astype(np.uint8))
    path.with_suffix(".mtl").write_text(f"newmtl material_0\nKd 1 1 1\nmap_Kd {png.name}\n")
    lines = [f"mtllib {path.with_suffix('.mtl').name}", "usemtl material_0"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices_m]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in mesh.uv]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")


def write_png(path: str | Path, array: np.ndarray) -> None:
    """An image as PNG with its own dtype (uint8 RGB or masks, uint16 BOP depth); not atomic (synth
    writes into a temporary folder that is renamed when complete)."""
    Image.fromarray(array).save(path)
