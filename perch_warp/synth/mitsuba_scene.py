"""The Mitsuba 3 scene of a planned image: sensor, objects, table, room and lights (metres; the
models are millimetres and scaled here). Mitsuba is imported on first use: it is an optional
dependency (`pip install perch_warp[synth]`) and takes seconds to import."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import PerchError
from ..scene import (
    cloth_texture,
    environment_map,
    floor_texture,
    laminate_texture,
    planked_wood_texture,
    plaster_texture,
)
from .plan import MITSUBA_VARIANT, Config, ImagePlan

_MI: Any = None
_TEX_CACHE: dict[str, Any] = {}


def mitsuba_module() -> Any:
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
        mi = mitsuba_module()
        _TEX_CACHE[path] = mi.load_dict({"type": "bitmap", "filename": path})
    return _TEX_CACHE[path]


def _bitmap(array: np.ndarray) -> dict:
    mi = mitsuba_module()
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(array, dtype=np.float32)), "raw": True}


def _transform(M: np.ndarray) -> Any:
    return mitsuba_module().ScalarTransform4f(np.asarray(M, dtype=np.float64).tolist())


def sensor_dict(cfg: Config, plan: ImagePlan, spp: int, pixel_centres: bool) -> dict:
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


def object_shape(cfg: Config, plan: ImagePlan, k: int, textured: bool, rng: np.random.Generator | None) -> dict:
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


def environment_shapes(rng: np.random.Generator, plan: ImagePlan) -> dict[str, dict]:
    """Table (top, legs), floor and one wall with procedural textures; the table top is z = 0."""
    sx, sy = rng.uniform(1.2, 1.8), rng.uniform(0.8, 1.2)
    table_bsdf = _table_top_bsdf(rng, sx, sy)
    thick = 0.03
    top = np.eye(4)
    top[:3, :3] = np.diag([sx / 2, sy / 2, thick / 2])
    top[2, 3] = -thick / 2
    shapes: dict[str, dict] = {"table": {"type": "cube", "to_world": _transform(top), "bsdf": table_bsdf}}
    height = rng.uniform(0.7, 0.8)
    shapes.update(_table_legs(sx, sy, thick, height))
    floor = np.eye(4)
    floor[:3, :3] = np.diag([3.0, 3.0, 1.0])
    floor[2, 3] = -height
    shapes["floor"] = {
        "type": "rectangle",
        "to_world": _transform(floor),
        "bsdf": {"type": "diffuse", "reflectance": _bitmap(floor_texture(rng, 512, 512))},
    }
    shapes["wall"] = _wall(rng, height)
    return shapes


def _table_top_bsdf(rng: np.random.Generator, sx: float, sy: float) -> dict:
    """The table top's material (sx x sy metres): planked wood (twice as likely), laminate or cloth, textured."""
    kind = rng.choice(["wood", "wood", "laminate", "cloth"])
    tex_w = 2048
    tex_h = int(tex_w * sy / sx)
    if kind == "wood":
        tex = planked_wood_texture(rng, tex_h, tex_w, (sx, sy))
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
    return table_bsdf


def _table_legs(sx: float, sy: float, thick: float, height: float) -> dict[str, dict]:
    """Four dark metal legs under a sx x sy top `thick` thick, reaching the floor `height` below its surface."""
    leg_bsdf = {
        "type": "principled",
        "base_color": {"type": "rgb", "value": [0.05, 0.05, 0.05]},
        "roughness": 0.3,
        "metallic": 0.6,
    }
    shapes = {}
    for i, (ax, ay) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        leg = np.eye(4)
        leg[:3, :3] = np.diag([0.025, 0.025, (height - thick) / 2])
        leg[:3, 3] = [ax * (sx / 2 - 0.06), ay * (sy / 2 - 0.06), -thick - (height - thick) / 2]
        shapes[f"leg{i}"] = {"type": "cube", "to_world": _transform(leg), "bsdf": leg_bsdf}
    return shapes


def _wall(rng: np.random.Generator, height: float) -> dict:
    """A plastered wall on a random side, facing the table, so low views see a room rather than only
    sky (the floor `height` below the table top)."""
    ang = rng.uniform(0, 2 * np.pi)
    d = rng.uniform(1.3, 2.2)
    n = np.array([math.cos(ang), math.sin(ang), 0.0])
    wall = np.eye(4)
    # Rectangle normal is +z: map x -> tangent, y -> world z, z -> -n (towards the table).
    tangent = np.cross(np.array([0.0, 0.0, 1.0]), -n)
    wall[:3, :3] = np.stack([tangent * 3.0, np.array([0.0, 0.0, 1.5]), -n], 1)
    wall[:3, 3] = d * n + np.array([0.0, 0.0, 1.5 - height])
    return {
        "type": "rectangle",
        "to_world": _transform(wall),
        "bsdf": {"type": "diffuse", "reflectance": _bitmap(plaster_texture(rng, 256, 512))},
    }


def light_shapes(rng: np.random.Generator, lighting: str, camera_height_m: float) -> dict[str, dict]:
    harsh = lighting == "harsh"
    env_rot = np.eye(4)
    c, s = math.cos(rng.uniform(0, 2 * np.pi)), math.sin(rng.uniform(0, 2 * np.pi))
    # Mitsuba's environment map has +y up; rotate it to the table frame's +z and spin it.
    to_z_up = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
    env_rot[:2, :2] = [[c, -s], [s, c]]
    lights: dict[str, dict] = {
        "env": {
            "type": "envmap",
            "bitmap": mitsuba_module().Bitmap(environment_map(rng, harsh)),
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
            "to_world": mitsuba_module()
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


def render_depth(scene_dict: dict) -> np.ndarray:
    """Ray length (m) at pixel centres; 0 where the ray hits nothing."""
    mi = mitsuba_module()
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "d:depth"}, **scene_dict})
    return np.array(mi.render(scene))[..., 0].astype(np.float64)
