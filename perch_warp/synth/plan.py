"""What is random about one synthetic image, drawn from its own RNG: which objects, where on the
table (table frame, millimetres, z = 0 the table top) and the camera (OpenCV, world to camera)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import PerchError
from ..scene import footprints_separated, look_at_camera, project
from ..table import rot_z
from .models import ModelSpec

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
            if all(footprints_separated(foot, p, margin) for p in placed):
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
