"""Photorealistic synthetic tabletop test scenes in BOP format, rendered with Mitsuba 3.

The images come from Mitsuba 3's path tracer (variant ``scalar_rgb``), a physically
based renderer that shares no code with the engine's own renderer, so a pose search
tested on them cannot profit from matching its own rendering model.

Every image is its own tabletop arrangement: 1-5 objects (at least one target) stand
upright in their resting pose (model +z along the table normal, lowest vertex on the
table top) at random x, y and yaw with non-intersecting footprints, seen by a camera
at a random distance, elevation, azimuth and slight roll. Scenes have a procedural
table (wood, laminate or cloth) on legs, a floor, a wall, a procedural indoor
environment map, and either soft lighting (large area light plus windows in the
environment, label ``normal``) or hard lighting (a spot light and a dim environment,
label ``harsh``). A camera-like post-process adds auto exposure, vignetting, shot and
read noise.

Output layout (``--out DIR``), BOP "test" split with all images in one scene folder::

    DIR/dataset_info.json            generator settings; "models_dir" = absolute path of the meshes used
    DIR/preview.png                  contact sheet of the first 8 images
    DIR/camera.json                  BOP camera file (intrinsics, depth_scale)
    DIR/test_targets_bop19.json      the target instances (BOP 19 format)
    DIR/test/000001/rgb/{im_id:06d}.png
    DIR/test/000001/depth/{im_id:06d}.png                 uint16, depth_scale 0.1 (mm = value * 0.1)
    DIR/test/000001/mask/{im_id:06d}_{gt_id:06d}.png      full silhouette of each instance
    DIR/test/000001/mask_visib/{im_id:06d}_{gt_id:06d}.png  its visible part
    DIR/test/000001/scene_camera.json
    DIR/test/000001/scene_gt.json
    DIR/test/000001/scene_gt_info.json

Image ids start at 1 (as in YCB-Video's BOP test split). ``scene_camera.json`` entries
hold ``cam_K`` (row-major), ``depth_scale``, the table frame ``cam_R_w2c``/``cam_t_w2c``
(mm; world z = table normal, z = 0 the table top) and two extra keys that BOP readers
ignore: ``"lighting": "normal"|"harsh"`` and ``"occlusion": "low"|"high"``.
``scene_gt_info.json`` counts pixels from Mitsuba-rendered masks (pixel-centre rays):
the full mask of an instance is a render of that object alone, the visible mask keeps
the pixels where that object is the nearest object surface.

The generator is deterministic for a seed: image ``i`` draws everything from an RNG
seeded with ``(seed, i)``, so results do not depend on the number of worker processes.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import bop
from .errors import PerchError

DEFAULT_TARGETS = (3, 4, 8, 9)
# YCB-Video's focal length; the renderer has square pixels, so fx = fy.
YCBV_FOCAL_640 = 1066.8
# Measured on the 2-core development CPU (docs/synthetic.md): 640x480 at 32 spp costs
# ~19 CPU-seconds per image (15-17 s of it path tracing), so 40 images take ~7 min on 2 cores.
DEFAULT_SPP = 32
MAX_PATH_DEPTH = 5
SCENE_ID = 1
IMAGE_ID_BASE = 1
DEPTH_SCALE = 0.1  # BOP depth png unit in mm, as in YCB-Video
MITSUBA_VARIANT = "scalar_rgb"  # the llvm_* variants crash on the development machines


# --------------------------------------------------------------------------- models


@dataclass(frozen=True)
class ModelSpec:
    """What the generator needs of one mesh; lengths in millimetres (BOP model units)."""

    obj_id: int
    obj_path: str
    texture_path: str | None
    min_z: float
    hull_xy: np.ndarray  # (K, 2) convex footprint, counter-clockwise
    bbox_corners: np.ndarray  # (8, 3)
    vertices: np.ndarray = field(repr=False)  # (N, 3), kept for the in-view check


def read_obj_vertices(path: Path) -> np.ndarray:
    """The ``v`` lines of a Wavefront OBJ as an (N, 3) float array."""
    rows = []
    try:
        with open(path) as f:
            for line in f:
                if line.startswith("v "):
                    rows.append(line.split()[1:4])
    except OSError as e:
        raise PerchError(f"cannot read model {path}: {e}") from None
    try:
        v = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise PerchError(f"model {path} has malformed vertex lines") from None
    if len(v) < 4 or not np.all(np.isfinite(v)):
        raise PerchError(f"model {path} has fewer than 4 finite vertices")
    return v


def _texture_of(obj_path: Path) -> str | None:
    """The diffuse texture named by the OBJ's material file, else ``<stem>.png`` beside it."""
    mtl = obj_path.with_suffix(".mtl")
    if mtl.is_file():
        for line in mtl.read_text(errors="replace").splitlines():
            parts = line.split()
            if len(parts) >= 2 and parts[0] == "map_Kd":
                tex = obj_path.parent / parts[-1]
                if tex.is_file():
                    return str(tex.resolve())
                raise PerchError(f"{mtl} names texture {parts[-1]}, which does not exist")
    png = obj_path.with_suffix(".png")
    return str(png.resolve()) if png.is_file() else None


def _convex_hull_ccw(points: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    return points[hull.vertices]  # scipy gives 2-D hull vertices counter-clockwise


def load_model(models_dir: Path, obj_id: int) -> ModelSpec:
    path = models_dir / f"obj_{obj_id:06d}.obj"
    if not path.is_file():
        raise PerchError(f"model for object id {obj_id} not found: {path}")
    v = read_obj_vertices(path)
    lo, hi = v.min(0), v.max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return ModelSpec(
        obj_id=obj_id,
        obj_path=str(path.resolve()),
        texture_path=_texture_of(path),
        min_z=float(lo[2]),
        hull_xy=_convex_hull_ccw(v[:, :2]),
        bbox_corners=corners,
        vertices=v,
    )


def available_ids(models_dir: Path) -> list[int]:
    ids = []
    for p in models_dir.glob("obj_*.obj"):
        try:
            ids.append(int(p.stem[4:]))
        except ValueError:
            continue
    return sorted(ids)


# --------------------------------------------------------------------------- geometry


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _separated(a: np.ndarray, b: np.ndarray, margin: float) -> bool:
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


# --------------------------------------------------------------------------- procedural textures


def _noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float]) -> np.ndarray:
    """Smooth value noise in [-1, 1]-ish: a coarse Gaussian grid upsampled with cubic splines."""
    from scipy.ndimage import zoom

    gh, gw = max(2, int(cells[0])), max(2, int(cells[1]))
    g = rng.standard_normal((gh + 3, gw + 3))
    fy, fx = shape[0] / gh, shape[1] / gw
    up = zoom(g, (fy, fx), order=3)  # (gh + 3) * fy >= shape[0] + 3 rows: crop off the edge effects
    oy, ox = int(fy), int(fx)
    return up[oy : oy + shape[0], ox : ox + shape[1]] / 1.5


def _fractal(
    rng: np.random.Generator, shape: tuple[int, int], cells: tuple[float, float], octaves: int = 4
) -> np.ndarray:
    from scipy.ndimage import zoom

    # Sum the octaves at a quarter of the resolution and upsample linearly: these fields are smooth,
    # and full-resolution cubic upsampling of every octave cost seconds per table texture.
    small = (-(-shape[0] // 4), -(-shape[1] // 4))
    out = np.zeros(small)
    amp = 1.0
    for o in range(octaves):
        out += amp * _noise(rng, small, (cells[0] * 2**o, cells[1] * 2**o))
        amp *= 0.5
    return zoom(out, 4, order=1)[: shape[0], : shape[1]]


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def wood_texture(rng: np.random.Generator, h: int, w: int, size_m: tuple[float, float]) -> np.ndarray:
    """Planked wood: grain along x, per-plank ring offsets and tint, dark seams; linear RGB."""
    palettes = [
        ((0.78, 0.60, 0.40), (0.55, 0.36, 0.20)),
        ((0.45, 0.30, 0.19), (0.26, 0.16, 0.09)),
        ((0.88, 0.76, 0.58), (0.70, 0.55, 0.37)),
        ((0.62, 0.42, 0.27), (0.40, 0.24, 0.13)),
    ]
    light, dark = (_srgb_to_linear(np.array(c)) for c in palettes[rng.integers(len(palettes))])
    ys = (np.arange(h, dtype=np.float32)[:, None] / h * size_m[1]).astype(np.float32)
    xs = (np.arange(w, dtype=np.float32)[None, :] / w * size_m[0]).astype(np.float32)
    plank_w = rng.uniform(0.09, 0.2)
    plank = np.floor(ys / plank_w).astype(int)  # (h, 1): planks run along x
    n_planks = int(plank.max()) + 1
    offs = rng.uniform(0, 50, n_planks).astype(np.float32)[plank]
    tint = rng.uniform(0.9, 1.1, n_planks).astype(np.float32)[plank]
    warp = _fractal(rng, (h, w), (6, 3), 3).astype(np.float32)
    ring_freq = np.float32(rng.uniform(25, 60))  # rings per metre across the grain
    rings = (ys * ring_freq + offs + 1.5 * warp + 0.15 * xs) % 1.0
    a = np.clip(np.abs(rings - 0.5) * 2, 0, 1)
    profile = a * a * np.sqrt(a)
    fibres = _noise(rng, (h, w), (h / 3, w / 80)).astype(np.float32)  # stretched along the grain
    t = np.clip(0.55 * profile + 0.12 * fibres + 0.15 * _fractal(rng, (h, w), (4, 4), 3) + 0.2, 0, 1)
    t = t.astype(np.float32)[..., None]
    rgb = (light * (1 - t) + dark * t) * tint[..., None]
    seam = ((ys % plank_w) < 0.0012)[:, 0]
    rgb[seam] *= 0.45
    return np.clip(rgb, 0, 1)


def laminate_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    base = np.array([[0.85, 0.85, 0.83], [0.62, 0.63, 0.62], [0.35, 0.36, 0.38], [0.80, 0.74, 0.64]])[rng.integers(4)]
    mottle = 0.04 * _fractal(rng, (h, w), (8, 8), 4)
    speck = (rng.random((h, w)) < 0.02) * rng.uniform(-0.25, 0.1, (h, w))
    rgb = base[None, None] * (1 + mottle + speck)[..., None]
    return np.clip(_srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


def cloth_texture(rng: np.random.Generator, h: int, w: int, size_m: tuple[float, float]) -> np.ndarray:
    base = np.array([[0.55, 0.12, 0.12], [0.20, 0.30, 0.50], [0.75, 0.72, 0.62], [0.25, 0.40, 0.28]])[rng.integers(4)]
    ys = np.arange(h)[:, None] / h * size_m[1]
    xs = np.arange(w)[None, :] / w * size_m[0]
    weave = 0.5 + 0.5 * np.sin(2 * np.pi * xs / 0.004) * np.sin(2 * np.pi * ys / 0.004)
    check = ((np.floor(xs / 0.06) + np.floor(ys / 0.06)) % 2) if rng.random() < 0.5 else np.zeros_like(xs + ys)
    shade = 0.88 + 0.06 * weave + 0.06 * _fractal(rng, (h, w), (10, 10), 3) - 0.25 * check
    rgb = base[None, None] * shade[..., None]
    return np.clip(_srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


def plaster_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    base = np.array([[0.80, 0.78, 0.72], [0.70, 0.75, 0.78], [0.85, 0.82, 0.78], [0.60, 0.62, 0.58]])[rng.integers(4)]
    rgb = base[None, None] * (1 + 0.05 * _fractal(rng, (h, w), (6, 6), 4))[..., None]
    return np.clip(_srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


def floor_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Large square tiles with grout lines and mottling (the floor is 6 m wide)."""
    base = np.array([[0.45, 0.42, 0.38], [0.30, 0.30, 0.32], [0.60, 0.55, 0.48]])[rng.integers(3)]
    ys, xs = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None] * 6.0
    grout = ((xs % 0.5) < 0.006) | ((ys % 0.5) < 0.006)
    rgb = base[None, None] * (1 + 0.08 * _fractal(rng, (h, w), (12, 12), 3))[..., None]
    rgb[grout] *= 0.6
    return np.clip(_srgb_to_linear(np.clip(rgb, 0, 1)), 0, 1)


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
    env = env * (1 + 0.15 * _fractal(rng, (h, w), (4, 8), 3))[..., None]
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


# --------------------------------------------------------------------------- scene sampling


@dataclass
class ImagePlan:
    """Everything random about one image, drawn from its own RNG."""

    im_id: int
    lighting: str
    occlusion: str
    obj_ids: list[int]
    R_m2w: list[np.ndarray]
    t_m2w_mm: list[np.ndarray]
    R_w2c: np.ndarray
    t_w2c_mm: np.ndarray
    render_seed: int
    attempt: int


@dataclass(frozen=True)
class Config:
    models: dict[int, ModelSpec]
    targets: tuple[int, ...]
    distractors: tuple[int, ...]
    lighting: str
    occlusion: str
    width: int
    height: int
    K: np.ndarray
    spp: int
    seed: int
    max_objects: int
    threads: int


def _labels(cfg: Config, index: int) -> tuple[str, str]:
    # "mixed" alternates so that a 40-image set holds every lighting/occlusion pair ten times.
    lighting = cfg.lighting if cfg.lighting != "mixed" else ("normal", "harsh")[index % 2]
    occlusion = cfg.occlusion if cfg.occlusion != "mixed" else ("low", "high")[(index // 2) % 2]
    return lighting, occlusion


def _pick_objects(rng: np.random.Generator, cfg: Config, occlusion: str) -> list[int]:
    lo = min(3, cfg.max_objects) if occlusion == "high" else 1
    n = int(rng.integers(lo, cfg.max_objects + 1))
    n_t = 1 + int(rng.binomial(n - 1, 0.5)) if cfg.distractors else n
    n_t = min(n_t, len(cfg.targets))
    n_d = min(n - n_t, len(cfg.distractors))
    ids = list(rng.choice(cfg.targets, n_t, replace=False)) + list(rng.choice(cfg.distractors, n_d, replace=False))
    return [int(i) for i in rng.permutation(ids)]


def _layout(
    rng: np.random.Generator, cfg: Config, ids: list[int], occlusion: str, view_dir: np.ndarray
) -> tuple[list[np.ndarray], list[np.ndarray]] | None:
    """Yaws and positions (mm) with footprints apart; None if the objects did not fit."""
    placed: list[np.ndarray] = []
    Rs: list[np.ndarray] = []
    ts: list[np.ndarray] = []
    side = np.array([-view_dir[1], view_dir[0]])
    for obj_id in ids:
        m = cfg.models[obj_id]
        radius = float(np.linalg.norm(m.hull_xy, axis=1).max())
        for _ in range(300):
            yaw = rng.uniform(-np.pi, np.pi)
            R = rot_z(yaw)
            if occlusion == "high" and placed:
                # Line objects up along the viewing direction so nearer ones hide farther ones.
                j = int(rng.integers(len(placed)))
                other = ts[j][:2]
                r_j = float(np.linalg.norm(placed[j] - other, axis=1).max())
                along = rng.choice([-1.0, 1.0]) * rng.uniform(0.7, 1.2) * (radius + r_j)
                lateral = rng.uniform(-0.45, 0.45) * (radius + r_j)
                xy = other + along * view_dir + lateral * side
                margin = 5.0
            else:
                reach = 50.0 + 35.0 * len(ids)
                xy = rng.uniform(-reach, reach, 2)
                margin = 30.0
            foot = m.hull_xy @ R[:2, :2].T + xy
            if all(_separated(foot, p, margin) for p in placed):
                placed.append(foot)
                Rs.append(R)
                ts.append(np.array([xy[0], xy[1], -m.min_z]))
                break
        else:
            return None
    centre = np.mean([t[:2] for t in ts], axis=0)
    for t in ts:  # keep the cluster near the table centre
        t[:2] -= centre
    return Rs, ts


def _in_view(cfg: Config, R_w2c: np.ndarray, t_w2c: np.ndarray, ids: list[int], Rs, ts, margin: float) -> bool:
    for obj_id, R, t in zip(ids, Rs, ts, strict=True):
        pts = cfg.models[obj_id].bbox_corners @ R.T + t
        pc = pts @ R_w2c.T + t_w2c
        if np.any(pc[:, 2] < 100.0):
            return False
        uv = project(cfg.K, R_w2c, t_w2c, pts)
        if (
            uv[:, 0].min() < margin
            or uv[:, 1].min() < margin
            or uv[:, 0].max() > cfg.width - 1 - margin
            or uv[:, 1].max() > cfg.height - 1 - margin
        ):
            return False
    return True


def plan_image(cfg: Config, index: int, attempt: int = 0) -> ImagePlan:
    """Objects, their poses and the camera of image ``index`` (deterministic in seed, index, attempt)."""
    rng = np.random.default_rng([cfg.seed, index, attempt])
    lighting, occlusion = _labels(cfg, index)
    for _ in range(100):
        ids = _pick_objects(rng, cfg, occlusion)
        azimuth = rng.uniform(-np.pi, np.pi)
        view_dir = np.array([-math.cos(azimuth), -math.sin(azimuth)])  # horizontal, camera -> scene
        lay = _layout(rng, cfg, ids, occlusion, view_dir)
        if lay is None:
            continue
        Rs, ts = lay
        elev_range = (15.0, 40.0) if occlusion == "high" else (30.0, 70.0)
        for _ in range(30):
            elevation = math.radians(rng.uniform(*elev_range))
            dist = rng.uniform(550.0, 1000.0)
            target = np.array([*rng.normal(0.0, 20.0, 2), rng.uniform(20.0, 80.0)])
            roll = math.radians(rng.normal(0.0, 3.0))
            for _grow in range(8):  # back off until every object is fully inside the frame
                offset = dist * np.array(
                    [
                        math.cos(elevation) * math.cos(azimuth),
                        math.cos(elevation) * math.sin(azimuth),
                        math.sin(elevation),
                    ]
                )
                R_w2c, t_w2c = look_at_camera(target + offset, target, roll)
                if _in_view(cfg, R_w2c, t_w2c, ids, Rs, ts, margin=4.0):
                    return ImagePlan(
                        IMAGE_ID_BASE + index,
                        lighting,
                        occlusion,
                        ids,
                        Rs,
                        ts,
                        R_w2c,
                        t_w2c,
                        int(rng.integers(0, 2**31 - 1)),
                        attempt,
                    )
                dist *= 1.12
                if dist > 1600.0:
                    break
    raise PerchError(
        f"could not place objects {ids} in view for image {index}: the models may be too large for "
        f"a {cfg.width}x{cfg.height} image with focal {cfg.K[0, 0]:.0f}px"
    )


# --------------------------------------------------------------------------- rendering (worker side)

_MI: Any = None
_TEX_CACHE: dict[str, Any] = {}


def _mitsuba() -> Any:
    global _MI
    if _MI is None:
        try:
            import mitsuba as mi
        except ImportError:
            raise PerchError("synth needs Mitsuba 3: pip install mitsuba") from None
        mi.set_variant(MITSUBA_VARIANT)
        # Mesh warnings (e.g. a degenerate vertex normal in a YCB model) would break the progress bar.
        mi.set_log_level(mi.LogLevel.Error)
        _MI = mi
    return _MI


def _texture(path: str) -> Any:
    # Decoding a 2048^2 PNG costs ~0.1 s; every image of a worker reuses the same few textures.
    if path not in _TEX_CACHE:
        mi = _mitsuba()
        _TEX_CACHE[path] = mi.load_dict({"type": "bitmap", "filename": path})
    return _TEX_CACHE[path]


def _bitmap(array: np.ndarray) -> dict:
    mi = _mitsuba()
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(array, dtype=np.float32)), "raw": True}


def _transform(M: np.ndarray) -> Any:
    return _mitsuba().ScalarTransform4f(np.asarray(M, dtype=np.float64).tolist())


def _sensor(cfg: Config, plan: ImagePlan, spp: int, pixel_centres: bool) -> dict:
    """Mitsuba perspective camera equal to the OpenCV one: Mitsuba's camera has x left, y up."""
    W, H = cfg.width, cfg.height
    fx, cx, cy = cfg.K[0, 0], cfg.K[0, 2], cfg.K[1, 2]
    R_c2w = plan.R_w2c.T
    M = np.eye(4)
    M[:3, :3] = R_c2w @ np.diag([-1.0, -1.0, 1.0])
    M[:3, 3] = -R_c2w @ (plan.t_w2c_mm / 1000.0)
    # Mitsuba film pixel i spans [i, i+1) with its centre at i + 0.5 = OpenCV's u + 0.5.
    sampler = (
        {"type": "stratified", "sample_count": 1, "jitter": False}
        if pixel_centres
        else {"type": "independent", "sample_count": spp, "seed": plan.render_seed}
    )
    return {
        "type": "perspective",
        "fov": float(np.degrees(2 * np.arctan(W / (2 * fx)))),
        "fov_axis": "x",
        "principal_point_offset_x": float(0.5 - (cx + 0.5) / W),
        "principal_point_offset_y": float(0.5 - (cy + 0.5) / H),
        "near_clip": 0.01,
        "far_clip": 100.0,
        "to_world": _transform(M),
        "sampler": sampler,
        "film": {
            "type": "hdrfilm",
            "width": W,
            "height": H,
            "pixel_format": "rgb",
            "rfilter": {"type": "box"} if pixel_centres else {"type": "gaussian"},
        },
    }


def _object_shape(cfg: Config, plan: ImagePlan, k: int, textured: bool, rng: np.random.Generator | None) -> dict:
    m = cfg.models[plan.obj_ids[k]]
    M = np.eye(4)
    M[:3, :3] = plan.R_m2w[k]
    M[:3, 3] = plan.t_m2w_mm[k] / 1000.0
    M = M @ np.diag([1e-3, 1e-3, 1e-3, 1.0])  # models are in mm, the scene in metres
    shape: dict[str, Any] = {"type": "obj", "filename": m.obj_path, "to_world": _transform(M)}
    if textured:
        assert rng is not None
        color: Any = _texture(m.texture_path) if m.texture_path else {"type": "rgb", "value": [0.5, 0.5, 0.5]}
        shape["bsdf"] = {
            "type": "principled",
            "base_color": color,
            "roughness": float(rng.uniform(0.3, 0.6)),
            "specular": float(rng.uniform(0.3, 0.6)),
        }
    return shape


def _environment_shapes(rng: np.random.Generator, plan: ImagePlan) -> dict[str, dict]:
    """Table (top, legs), floor and one wall with procedural textures; the table top is z = 0."""
    T = np.eye(4)
    sx, sy = rng.uniform(1.2, 1.8), rng.uniform(0.8, 1.2)
    kind = rng.choice(["wood", "wood", "laminate", "cloth"])
    tex_w = 2048
    tex_h = int(tex_w * sy / sx)
    if kind == "wood":
        tex = wood_texture(rng, tex_h, tex_w, (sx, sy))
        table_bsdf = {
            "type": "principled",
            "roughness": float(rng.uniform(0.25, 0.55)),
            "specular": float(rng.uniform(0.4, 0.6)),
        }
    elif kind == "laminate":
        tex = laminate_texture(rng, tex_h, tex_w)
        table_bsdf = {"type": "principled", "roughness": float(rng.uniform(0.2, 0.45)), "specular": 0.5}
    else:
        tex = cloth_texture(rng, tex_h, tex_w, (sx, sy))
        table_bsdf = {"type": "diffuse"}
    key = "base_color" if table_bsdf["type"] == "principled" else "reflectance"
    table_bsdf[key] = _bitmap(tex)
    thick = 0.03
    top = T.copy()
    top[:3, :3] = np.diag([sx / 2, sy / 2, thick / 2])
    top[2, 3] = -thick / 2
    shapes: dict[str, dict] = {"table": {"type": "cube", "to_world": _transform(top), "bsdf": table_bsdf}}
    leg_bsdf = {
        "type": "principled",
        "base_color": {"type": "rgb", "value": [0.05, 0.05, 0.05]},
        "roughness": 0.3,
        "metallic": 0.6,
    }
    height = rng.uniform(0.7, 0.8)
    for i, (ax, ay) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        leg = np.eye(4)
        leg[:3, :3] = np.diag([0.025, 0.025, (height - thick) / 2])
        leg[:3, 3] = [ax * (sx / 2 - 0.06), ay * (sy / 2 - 0.06), -thick - (height - thick) / 2]
        shapes[f"leg{i}"] = {"type": "cube", "to_world": _transform(leg), "bsdf": leg_bsdf}
    floor = np.eye(4)
    floor[:3, :3] = np.diag([3.0, 3.0, 1.0])
    floor[2, 3] = -height
    shapes["floor"] = {
        "type": "rectangle",
        "to_world": _transform(floor),
        "bsdf": {"type": "diffuse", "reflectance": _bitmap(floor_texture(rng, 512, 512))},
    }
    # A wall on a random side, facing the table, so low views see a room rather than only sky.
    ang = rng.uniform(0, 2 * np.pi)
    d = rng.uniform(1.3, 2.2)
    n = np.array([math.cos(ang), math.sin(ang), 0.0])
    wall = np.eye(4)
    # Rectangle normal is +z: map x -> tangent, y -> world z, z -> -n (towards the table).
    tangent = np.cross(np.array([0.0, 0.0, 1.0]), -n)
    wall[:3, :3] = np.stack([tangent * 3.0, np.array([0.0, 0.0, 1.5]), -n], 1)
    wall[:3, 3] = d * n + np.array([0.0, 0.0, 1.5 - height])
    shapes["wall"] = {
        "type": "rectangle",
        "to_world": _transform(wall),
        "bsdf": {"type": "diffuse", "reflectance": _bitmap(plaster_texture(rng, 256, 512))},
    }
    return shapes


def _lights(rng: np.random.Generator, lighting: str, camera_height_m: float) -> dict[str, dict]:
    harsh = lighting == "harsh"
    env_rot = np.eye(4)
    c, s = math.cos(rng.uniform(0, 2 * np.pi)), math.sin(rng.uniform(0, 2 * np.pi))
    # Mitsuba's environment map has +y up; rotate it to the table frame's +z and spin it.
    to_z_up = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
    env_rot[:2, :2] = [[c, -s], [s, c]]
    lights: dict[str, dict] = {
        "env": {
            "type": "envmap",
            "bitmap": _mitsuba().Bitmap(environment_map(rng, harsh)),
            "scale": float(rng.uniform(0.04, 0.12) if harsh else rng.uniform(0.6, 1.0)),
            "to_world": _transform(env_rot @ to_z_up),
        },
    }
    tint = np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.7, 1.0)]) if rng.random() < 0.6 else np.ones(3)
    if harsh:
        az, el, d = rng.uniform(0, 2 * np.pi), math.radians(rng.uniform(25, 55)), rng.uniform(1.0, 1.8)
        pos = d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        aim = np.array([*rng.normal(0, 0.1, 2), 0.0])
        lights["spot"] = {
            "type": "spot",
            "intensity": {"type": "rgb", "value": (tint * 12.0 * d * d).tolist()},
            "cutoff_angle": float(rng.uniform(25, 40)),
            "beam_width": float(rng.uniform(12, 20)),
            "to_world": _mitsuba()
            .ScalarTransform4f()
            .look_at(origin=pos.tolist(), target=aim.tolist(), up=[0.0, 0.0, 1.0]),
        }
    else:
        size = rng.uniform(0.25, 0.5)
        panel = np.eye(4)
        # A downward-facing ceiling panel: turn the rectangle's +z normal over (a rotation, det > 0).
        panel[:3, :3] = np.diag([size, -size, -1.0])
        # Above the camera: a panel between camera and table would hide the scene.
        panel[:3, 3] = [*rng.uniform(-0.6, 0.6, 2), max(rng.uniform(1.0, 1.6), camera_height_m + 0.3)]
        lights["panel"] = {
            "type": "rectangle",
            "to_world": _transform(panel),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": (tint * rng.uniform(6, 14)).tolist()}},
        }
    return lights


def _render_depth(scene_dict: dict) -> np.ndarray:
    """Ray length (m) at pixel centres; 0 where the ray hits nothing."""
    mi = _mitsuba()
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "d:depth"}, **scene_dict})
    return np.array(mi.render(scene))[..., 0].astype(np.float64)


def _bbox(mask: np.ndarray) -> list[int]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


def _masks(cfg: Config, plan: ImagePlan) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Full and visible masks of every instance from pixel-centre depth renders of each object alone."""
    sensor = _sensor(cfg, plan, 1, pixel_centres=True)
    depths = [
        _render_depth({"sensor": sensor, "obj": _object_shape(cfg, plan, k, False, None)})
        for k in range(len(plan.obj_ids))
    ]
    full = [d > 0 for d in depths]
    stack = np.stack([np.where(f, d, np.inf) for f, d in zip(full, depths, strict=True)])
    nearest = stack.min(0)
    # Same rays in every render, so "this object is the nearest object here" is an exact comparison
    # up to float noise; the table and room never lie in front of an object standing on the table.
    visib = [f & (d <= nearest + 1e-5) for f, d in zip(full, depths, strict=True)]
    return full, visib


def _postprocess(rng: np.random.Generator, radiance: np.ndarray, harsh: bool) -> np.ndarray:
    """Linear radiance to an 8-bit sRGB image like a camera's: auto exposure, vignetting, shot/read noise."""
    from scipy.ndimage import median_filter

    lum = radiance @ np.array([0.2126, 0.7152, 0.0722])
    # Low sample counts leave isolated fireflies (glossy paths that hit a lamp) that no camera shows.
    med = median_filter(lum, size=3)
    fire = lum > 4.0 * med + 0.05
    radiance = np.where(fire[..., None], radiance * (med / np.maximum(lum, 1e-9))[..., None], radiance)
    lum = np.where(fire, med, lum)
    # Exposure from the log-average luminance (robust to a bright lamp or window in view), capped so
    # that most of the image stays below white; harsh light is exposed darker for contrast.
    log_avg = float(np.exp(np.mean(np.log(lum + 1e-4))))
    key = rng.uniform(0.10, 0.16) if harsh else rng.uniform(0.16, 0.22)
    scale = min(key / max(log_avg, 1e-6), 0.95 / max(float(np.percentile(lum, 90.0)), 1e-6))
    x = radiance * scale
    h, w = lum.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    x *= (1.0 - rng.uniform(0.05, 0.2) * r2)[..., None]
    x = np.clip(x, 0, None)
    shot = rng.uniform(0.0001, 0.0004)
    read = rng.uniform(0.0005, 0.002)
    x = x + rng.standard_normal(x.shape) * np.sqrt(shot * x + read**2)
    x = np.clip(x, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)


def _write_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(array).save(path)


def render_image(cfg: Config, index: int, scene_dir: str) -> dict:
    """Render image ``index`` into ``scene_dir``; returns its JSON entries and timings."""
    mi = _mitsuba()
    t0 = time.perf_counter()
    # Retry the arrangement when a target would be nearly hidden: a test image of a target
    # nobody can see tests nothing.
    for attempt in range(12):
        plan = plan_image(cfg, index, attempt)
        full, visib = _masks(cfg, plan)
        counts = [(int(f.sum()), int(v.sum())) for f, v in zip(full, visib, strict=True)]
        ok = all(
            a > 0 and (v / a >= 0.15 or oid not in cfg.targets) and v > 0
            for oid, (a, v) in zip(plan.obj_ids, counts, strict=True)
        )
        if ok:
            break
    t_masks = time.perf_counter() - t0
    rng = np.random.default_rng([cfg.seed, index, plan.attempt, 1])
    shapes = _environment_shapes(rng, plan)
    objects = {f"obj{k}": _object_shape(cfg, plan, k, True, rng) for k in range(len(plan.obj_ids))}
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": MAX_PATH_DEPTH},
            "sensor": _sensor(cfg, plan, cfg.spp, pixel_centres=False),
            **shapes,
            **objects,
            **_lights(rng, plan.lighting, float(-plan.R_w2c[:, 2] @ plan.t_w2c_mm) / 1000.0),
        }
    )
    t1 = time.perf_counter()
    radiance = np.array(mi.render(scene, seed=plan.render_seed, spp=cfg.spp))[..., :3].astype(np.float64)
    t_rgb = time.perf_counter() - t1
    rgb = _postprocess(rng, radiance, plan.lighting == "harsh")

    # BOP depth: z along the optical axis from the ray length at each pixel centre.
    t_ray = _render_depth({"sensor": _sensor(cfg, plan, 1, pixel_centres=True), **shapes, **objects})
    K = cfg.K
    u, v = np.meshgrid(np.arange(cfg.width), np.arange(cfg.height))
    norm = np.sqrt(((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
    depth = np.round(t_ray / norm * 1000.0 / DEPTH_SCALE)
    depth = np.where((depth > 0) & (depth < 65535), depth, 0).astype(np.uint16)

    d = Path(scene_dir)
    im_id = plan.im_id
    _write_png(d / "rgb" / f"{im_id:06d}.png", rgb)
    _write_png(d / "depth" / f"{im_id:06d}.png", depth)
    gt, info = [], []
    for k, obj_id in enumerate(plan.obj_ids):
        R_m2c = plan.R_w2c @ plan.R_m2w[k]
        t_m2c = plan.R_w2c @ plan.t_m2w_mm[k] + plan.t_w2c_mm
        gt.append({"obj_id": obj_id, "cam_R_m2c": R_m2c.reshape(-1).tolist(), "cam_t_m2c": t_m2c.tolist()})
        n_all, n_vis = counts[k]
        info.append(
            {
                "bbox_obj": _bbox(full[k]),
                "bbox_visib": _bbox(visib[k]),
                "px_count_all": n_all,
                "px_count_valid": n_all,
                "px_count_visib": n_vis,
                "visib_fract": float(n_vis / n_all) if n_all else 0.0,
            }
        )
        _write_png(d / "mask" / f"{im_id:06d}_{k:06d}.png", full[k].astype(np.uint8) * 255)
        _write_png(d / "mask_visib" / f"{im_id:06d}_{k:06d}.png", visib[k].astype(np.uint8) * 255)
    camera = {
        "cam_K": K.reshape(-1).tolist(),
        "depth_scale": DEPTH_SCALE,
        "cam_R_w2c": plan.R_w2c.reshape(-1).tolist(),
        "cam_t_w2c": plan.t_w2c_mm.tolist(),
        "lighting": plan.lighting,
        "occlusion": plan.occlusion,
    }
    return {
        "im_id": im_id,
        "camera": camera,
        "gt": gt,
        "info": info,
        "seconds": {"masks": t_masks, "rgb": t_rgb, "total": time.perf_counter() - t0},
    }


_WORKER_CFG: Config | None = None


def _worker_init(cfg: Config) -> None:
    global _WORKER_CFG
    _WORKER_CFG = cfg
    import drjit as dr

    _mitsuba()
    dr.set_thread_count(cfg.threads)


def _worker_render(job: tuple[int, str]) -> dict:
    assert _WORKER_CFG is not None
    return render_image(_WORKER_CFG, *job)


# --------------------------------------------------------------------------- driver


def write_preview(root: str | Path, path: str | Path | None = None, n: int = 8, columns: int = 4) -> Path:
    """A contact sheet of the first ``n`` images of a generated dataset, labelled with id, lighting, occlusion."""
    from PIL import Image, ImageDraw

    root = Path(root)
    scene = root / "test" / f"{SCENE_ID:06d}"
    cams = bop.read_json(scene / "scene_camera.json", "scene_camera.json")
    gts = bop.read_json(scene / "scene_gt.json", "scene_gt.json")
    tiles = []
    for im_id in sorted(cams, key=int)[:n]:
        im = Image.open(scene / "rgb" / f"{int(im_id):06d}.png").convert("RGB")
        if im.width > 320:
            im = im.resize((320, round(im.height * 320 / im.width)), Image.Resampling.LANCZOS)
        cam = cams[im_id]
        label = f"{im_id} {cam.get('lighting')} {cam.get('occlusion')} {[g['obj_id'] for g in gts[im_id]]}"
        draw = ImageDraw.Draw(im)
        draw.rectangle((0, 0, 7 * len(label), 12), fill=(0, 0, 0))
        draw.text((2, 0), label, fill=(255, 255, 0))
        tiles.append(im)
    cols = min(columns, len(tiles))
    rows = -(-len(tiles) // cols)
    w, h = tiles[0].size
    sheet = Image.new("RGB", (w * cols, h * rows))
    for k, im in enumerate(tiles):
        sheet.paste(im, ((k % cols) * w, (k // cols) * h))
    out = Path(path) if path is not None else root / "preview.png"
    sheet.save(out)
    return out


def generate(
    models_dir: str | Path,
    out_dir: str | Path,
    n_images: int,
    seed: int = 0,
    targets: tuple[int, ...] | list[int] = DEFAULT_TARGETS,
    distractors: list[int] | None = None,
    lighting: str = "mixed",
    occlusion: str = "mixed",
    width: int = 640,
    height: int = 480,
    focal: float | None = None,
    spp: int = DEFAULT_SPP,
    workers: int | None = None,
    max_objects: int = 5,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Render ``n_images`` tabletop images into a BOP dataset at ``out_dir``; returns a summary.

    ``distractors=None`` uses every other model in ``models_dir``. The dataset appears at
    ``out_dir`` only when complete (it is built in a temporary sibling folder).
    """
    models_dir = Path(models_dir)
    out_dir = Path(out_dir)
    if not models_dir.is_dir():
        raise PerchError(f"models directory not found: {models_dir}")
    if n_images < 1:
        raise PerchError(f"--scenes must be at least 1, got {n_images}")
    if lighting not in ("normal", "harsh", "mixed"):
        raise PerchError(f"--lighting must be normal, harsh or mixed, got {lighting!r}")
    if occlusion not in ("low", "high", "mixed"):
        raise PerchError(f"--occlusion must be low, high or mixed, got {occlusion!r}")
    if width < 16 or height < 16:
        raise PerchError(f"image size must be at least 16x16, got {width}x{height}")
    if spp < 1:
        raise PerchError(f"--spp must be at least 1, got {spp}")
    if not 1 <= max_objects <= 10:
        raise PerchError(f"--max-objects must be within 1..10, got {max_objects}")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise PerchError(f"output directory {out_dir} is not empty; pass --overwrite to replace it")
    found = available_ids(models_dir)
    if not found:
        raise PerchError(f"no BOP meshes (obj_NNNNNN.obj) in {models_dir}")
    targets = tuple(int(t) for t in targets)
    if not targets:
        raise PerchError("at least one target object id is needed (--objects)")
    for t in targets:
        if t not in found:
            raise PerchError(f"target object id {t} has no mesh obj_{t:06d}.obj in {models_dir}")
    if len(set(targets)) != len(targets):
        raise PerchError(f"--objects lists an id twice: {list(targets)}")
    if distractors is None:
        distractors = [i for i in found if i not in targets]
    for d in distractors:
        if d not in found:
            raise PerchError(f"distractor object id {d} has no mesh obj_{d:06d}.obj in {models_dir}")
        if d in targets:
            raise PerchError(f"object id {d} is both a target and a distractor")
    try:
        import mitsuba  # noqa: F401  (fail here, once, rather than in every worker)
    except ImportError:
        raise PerchError("synth needs Mitsuba 3: pip install mitsuba") from None

    models = {i: load_model(models_dir, i) for i in (*targets, *distractors)}
    f = focal if focal is not None else YCBV_FOCAL_640 * width / 640.0
    # YCB-Video's principal point, scaled to the image size.
    cx = (312.9869 + 0.5) * width / 640.0 - 0.5
    cy = (241.3109 + 0.5) * height / 480.0 - 0.5
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    n_workers = max(1, min(workers or os.cpu_count() or 1, n_images))
    # One single-threaded render per core also overlaps the ~2.5 s of serial per-image work
    # (textures, scene loading, PNGs) that a multi-threaded render leaves idle; a lone worker uses every core.
    threads = 1 if n_workers > 1 else (os.cpu_count() or 1)
    cfg = Config(
        models,
        targets,
        tuple(int(d) for d in distractors),
        lighting,
        occlusion,
        width,
        height,
        K,
        spp,
        int(seed),
        max_objects,
        threads,
    )

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        scene_dir = tmp / "test" / f"{SCENE_ID:06d}"
        for sub in ("rgb", "depth", "mask", "mask_visib"):
            (scene_dir / sub).mkdir(parents=True)
        jobs = [(i, str(scene_dir)) for i in range(n_images)]
        results = _run_jobs(cfg, jobs, n_workers, progress)
        results.sort(key=lambda r: r["im_id"])
        bop.write_scene(
            scene_dir,
            {r["im_id"]: r["camera"] for r in results},
            {r["im_id"]: r["gt"] for r in results},
            {r["im_id"]: r["info"] for r in results},
        )
        bop.write_json(
            tmp / "camera.json",
            {"cx": cx, "cy": cy, "fx": f, "fy": f, "width": width, "height": height, "depth_scale": DEPTH_SCALE},
        )
        bop.write_json(
            tmp / "test_targets_bop19.json",
            [
                {"im_id": r["im_id"], "inst_count": 1, "obj_id": g["obj_id"], "scene_id": SCENE_ID}
                for r in results
                for g in r["gt"]
                if g["obj_id"] in targets
            ],
        )
        secs = [r["seconds"]["total"] for r in results]
        import mitsuba as mi

        info = {
            "generator": "perch_warp.synth",
            "renderer": f"mitsuba {mi.__version__} {MITSUBA_VARIANT}",
            "models_dir": str(models_dir.resolve()),
            "split": "test",
            "scene_ids": [SCENE_ID],
            "image_id_base": IMAGE_ID_BASE,
            "n_images": n_images,
            "seed": int(seed),
            "targets": list(targets),
            "distractors": list(cfg.distractors),
            "lighting": lighting,
            "occlusion": occlusion,
            "width": width,
            "height": height,
            "cam_K": K.reshape(-1).tolist(),
            "spp": spp,
            "max_path_depth": MAX_PATH_DEPTH,
            "depth_scale": DEPTH_SCALE,
            "units": "mm",
            "labels": "scene_camera.json entries carry 'lighting' (normal|harsh) and 'occlusion' (low|high)",
        }
        bop.write_json(tmp / "dataset_info.json", info)
        write_preview(tmp)
        if out_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
            out_dir.rename(old / "d")
            tmp.rename(out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {
        "out": str(out_dir),
        "images": n_images,
        "workers": n_workers,
        "seconds_per_image_mean": float(np.mean(secs)),
        "seconds_per_image_max": float(np.max(secs)),
    }


def _run_jobs(cfg: Config, jobs: list[tuple[int, str]], n_workers: int, progress: bool) -> list[dict]:
    from tqdm import tqdm

    bar = tqdm(total=len(jobs), desc="synth", unit="img", disable=not progress)
    results = []
    try:
        if n_workers == 1:
            _worker_init(cfg)
            for job in jobs:
                results.append(_worker_render(job))
                bar.update()
        else:
            import multiprocessing as mp

            # spawn: Mitsuba/Dr.Jit keep thread pools that do not survive fork.
            with mp.get_context("spawn").Pool(n_workers, initializer=_worker_init, initargs=(cfg,)) as pool:
                for r in pool.imap_unordered(_worker_render, jobs):
                    results.append(r)
                    bar.update()
    finally:
        bar.close()
    return results


# --------------------------------------------------------------------------- CLI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", required=True, help="BOP models folder with obj_NNNNNN.obj (+ .mtl/.png), mm")
    parser.add_argument("--out", required=True, help="dataset folder to create (BOP layout, see docs/synthetic.md)")
    parser.add_argument("--scenes", type=int, required=True, help="number of images (each its own arrangement)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--objects",
        type=int,
        nargs="+",
        default=list(DEFAULT_TARGETS),
        help="target object ids, at least one per image (default 3 4 8 9)",
    )
    parser.add_argument(
        "--distractors",
        type=int,
        nargs="*",
        default=None,
        help="distractor ids (default: every other model; give none for no distractors)",
    )
    parser.add_argument("--lighting", choices=("normal", "harsh", "mixed"), default="mixed")
    parser.add_argument("--occlusion", choices=("low", "high", "mixed"), default="mixed")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument(
        "--focal",
        type=float,
        default=None,
        help="focal length in pixels, fx = fy (default YCB-Video's 1066.8, scaled to --width)",
    )
    parser.add_argument("--spp", type=int, default=DEFAULT_SPP, help=f"samples per pixel (default {DEFAULT_SPP})")
    parser.add_argument("--max-objects", type=int, default=5, help="objects per image at most (default 5)")
    parser.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    summary = generate(
        args.models,
        args.out,
        args.scenes,
        seed=args.seed,
        targets=args.objects,
        distractors=args.distractors,
        lighting=args.lighting,
        occlusion=args.occlusion,
        width=args.width,
        height=args.height,
        focal=args.focal,
        spp=args.spp,
        workers=args.workers,
        max_objects=args.max_objects,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    print(
        f"wrote {summary['images']} images to {summary['out']} in {time.perf_counter() - t0:.1f} s "
        f"({summary['workers']} workers, {summary['seconds_per_image_mean']:.1f} s per image per worker)"
    )
    return 0
