"""A shaded, shadowed, noisy photo of a whole scene: the demo's offline "camera" (perch_warp.demo).

It deliberately differs from kernel #1 (kernels are in photo_kernels.py): Lambertian + specular
lighting from a point light, hard shadows, colour cast, gamma, blur and sensor noise, so that the
engine recovering a pose from it is a real test. Poses are model -> camera (metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .camera import Camera
from .kernels.render import MeshLook
from .mesh import ObjectMesh
from .mipmap import set_mip
from .photo_kernels import primary_pass, shadow_pass


@dataclass
class Placed:
    """A mesh placed in the scene: model -> camera (metres)."""

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
    """A lit, shadowed, noisy uint8 photo of the scene, and the per-pixel index of the visible mesh (-1: none).
    `light_c_m`: the point light in the camera frame, metres."""
    d, a, n, lab, s = _cast(scene, camera, light_c_m, device)
    img = _shade(camera, light_c_m, d, a, n, lab, s)
    # Optics blur (3x3 binomial) and sensor noise.
    k = np.array([1.0, 2.0, 1.0]) / 4
    img = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 0, img)
    img = np.apply_along_axis(lambda r: np.convolve(r, k, mode="same"), 1, img)
    img = img * 255 + rng.normal(0, noise_sigma, img.shape)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8), lab


def _look(m: ObjectMesh, idx: wp.array) -> MeshLook:
    """The mesh's appearance struct on the current device (dummies for the form it does not use)."""
    tex = m.texture is not None
    look = MeshLook()
    look.indices = idx
    look.uvs = wp.array(m.uv if tex else np.zeros((1, 2), np.float32), dtype=wp.vec2)
    look.texture = wp.array(m.texture if tex else np.zeros((1, 1, 3), np.float32), dtype=wp.vec3)
    look.colors = wp.array(m.vertex_colors if not tex else np.zeros((1, 3), np.float32), dtype=wp.vec3)
    look.use_texture = int(tex)
    set_mip(look, None)  # the photographer reads textures as the thesis's render does
    return look


def _cast(scene: list[Placed], camera: Camera, light_c_m: np.ndarray, device: str) -> tuple[np.ndarray, ...]:
    """Per pixel, from one ray through its centre: depth (m along the ray), albedo, normal, the index of
    the nearest mesh (-1: none) and whether the light sees that point (1) or not (0)."""
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
            wp.launch(
                primary_pass,
                dim=(H, W),
                inputs=[wm.id, _look(m, idx), camera.fx, camera.fy, camera.cx, camera.cy],
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
        return depth.numpy(), albedo.numpy(), normal.numpy(), label.numpy(), lit.numpy()


def _shade(camera: Camera, light_c_m, d, a, n, lab, s) -> np.ndarray:
    """Shading on the host: Lambert + Blinn-Phong highlight, ambient fill, warm colour cast, gamma;
    float RGB (H, W, 3) in [0, 1] with a graded background where no mesh is."""
    H, W = camera.height, camera.width
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
    return np.clip(img * np.array([1.06, 1.0, 0.9]), 0, 1) ** (1 / 1.1)
