"""Rendering one synthetic image in a worker: masks, the path-traced photo, BOP depth and the
image's BOP entries (millimetres)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from scipy.ndimage import median_filter

from ..scene import write_png
from .mitsuba_scene import environment_shapes, light_shapes, mitsuba_module, object_shape, render_depth, sensor_dict
from .plan import DEPTH_SCALE, MAX_PATH_DEPTH, Config, ImagePlan, plan_image


def _bbox(mask: np.ndarray) -> list[int]:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


def _masks(cfg: Config, plan: ImagePlan) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Full and visible masks of every instance from pixel-centre depth renders of each object alone."""
    sensor = sensor_dict(cfg, plan, 1, pixel_centres=True)
    depths = [
        render_depth({"sensor": sensor, "obj": object_shape(cfg, plan, k, False, None)})
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


def bop_depth(cfg: Config, t_ray: np.ndarray) -> np.ndarray:
    """BOP depth (uint16, DEPTH_SCALE mm units; 0 where nothing or out of range): z along the optical
    axis from the ray length t_ray (m) at each pixel centre."""
    K = cfg.K
    u, v = np.meshgrid(np.arange(cfg.width), np.arange(cfg.height))
    norm = np.sqrt(((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
    depth = np.round(t_ray / norm * 1000.0 / DEPTH_SCALE)
    return np.where((depth > 0) & (depth < 65535), depth, 0).astype(np.uint16)


def _instances(plan: ImagePlan, full: list, visib: list, counts: list, d: Path) -> tuple[list[dict], list[dict]]:
    """Each instance's scene_gt entry (model -> camera, mm) and scene_gt_info entry; writes its masks."""
    im_id = plan.im_id
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
        write_png(d / "mask" / f"{im_id:06d}_{k:06d}.png", full[k].astype(np.uint8) * 255)
        write_png(d / "mask_visib" / f"{im_id:06d}_{k:06d}.png", visib[k].astype(np.uint8) * 255)
    return gt, info


def _visible_plan(cfg: Config, index: int) -> tuple[ImagePlan, list, list, list[tuple[int, int]]]:
    """Image index's plan, its instances' full and visible masks and their pixel counts (all, visible).
    The arrangement is redrawn (up to 12 times) while a target would be nearly hidden: a test image
    of a target nobody can see tests nothing."""
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
    return plan, full, visib, counts


def render_image(cfg: Config, index: int, scene_dir: str) -> dict:
    """Render image ``index`` into ``scene_dir``; returns its JSON entries and timings."""
    mi = mitsuba_module()
    t0 = time.perf_counter()
    plan, full, visib, counts = _visible_plan(cfg, index)
    t_masks = time.perf_counter() - t0
    rng = np.random.default_rng([cfg.seed, index, plan.attempt, 1])
    shapes = environment_shapes(rng, plan)
    objects = {f"obj{k}": object_shape(cfg, plan, k, True, rng) for k in range(len(plan.obj_ids))}
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": MAX_PATH_DEPTH},
            "sensor": sensor_dict(cfg, plan, cfg.spp, pixel_centres=False),
            **shapes,
            **objects,
            **light_shapes(rng, plan.lighting, float(-plan.R_w2c[:, 2] @ plan.t_w2c_mm) / 1000.0),
        }
    )
    t1 = time.perf_counter()
    radiance = np.array(mi.render(scene, seed=plan.render_seed, spp=cfg.spp))[..., :3].astype(np.float64)
    t_rgb = time.perf_counter() - t1
    rgb = _postprocess(rng, radiance, plan.lighting == "harsh")

    t_ray = render_depth({"sensor": sensor_dict(cfg, plan, 1, pixel_centres=True), **shapes, **objects})
    d = Path(scene_dir)
    im_id = plan.im_id
    write_png(d / "rgb" / f"{im_id:06d}.png", rgb)
    write_png(d / "depth" / f"{im_id:06d}.png", bop_depth(cfg, t_ray))
    gt, info = _instances(plan, full, visib, counts, d)
    camera = {
        "cam_K": cfg.K.reshape(-1).tolist(),
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


def worker_init(cfg: Config) -> None:
    global _WORKER_CFG
    _WORKER_CFG = cfg
    import drjit as dr  # Mitsuba's array library: optional like Mitsuba itself (mitsuba_scene.py)

    mitsuba_module()
    dr.set_thread_count(cfg.threads)


def worker_render(job: tuple[int, str]) -> dict:
    assert _WORKER_CFG is not None
    return render_image(_WORKER_CFG, *job)
