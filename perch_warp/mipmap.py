"""Mip-mapped texture lookups for kernel #1 (issue 17 (f), score term ``texture=mip``).

A camera pixel averages the surface it sees; kernel #1 casts one ray per pixel and reads the
texture there. Where a pixel covers many texels (a 2048² YCB texture on a 10 cm object seen from
0.8 m: about 7 texels across a pixel), that one bilinear lookup picks an arbitrary texel, so the
render is noisier than the photo of the same surface (aliasing), and conv1's edge filters respond
to the noise. With mip-mapping each hit is read from a pre-averaged copy of the texture whose
texel is as wide as the pixel's footprint there (kernels/render.py: texture_lod, sample_mip):

* the pyramid: level 0 is the texture, level l + 1 the box average of level l over 2 x 2 texels
  (an odd side is averaged over the exact share of each texel, so every level keeps the mean);
* per face, its unit normal (model frame) and its texels per metre at level 0:
  sqrt(texel area / surface area) of the triangle, so a pixel footprint of s metres covers
  about s x that texels across, and the level is log2 of it.

The silhouette is unchanged (only colours are filtered), so the pruned search's bound is too.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .kernels.render import MeshLook


def halve(a: np.ndarray, axis: int) -> np.ndarray:
    """`a` averaged to max(1, n // 2) samples along `axis` (n its length there), each new sample
    the mean of the old ones over its interval [i n / m, (i + 1) n / m), old samples weighted by
    their overlap; for even n that is the mean of each pair."""
    n = a.shape[axis]
    m = max(1, n // 2)
    if n == 1:
        return a
    if n % 2 == 0:
        a = np.moveaxis(a, axis, 0)
        out = 0.5 * (a[0::2] + a[1::2])
        return np.moveaxis(out, 0, axis)
    r = n / m  # each new sample spans r old ones
    w = np.zeros((m, n))
    for i in range(m):
        lo, hi = i * r, (i + 1) * r
        for j in range(int(np.floor(lo)), min(n, int(np.ceil(hi)))):
            w[i, j] = (min(hi, j + 1) - max(lo, j)) / r
    return np.moveaxis(np.tensordot(w, np.moveaxis(a, axis, 0), axes=(1, 0)), 0, axis).astype(a.dtype)


def pyramid(texture: np.ndarray) -> list[np.ndarray]:
    """The mip levels of `texture` (H, W, 3) float32, level 0 first, down to 1 x 1."""
    levels = [np.ascontiguousarray(texture, dtype=np.float32)]
    while levels[-1].shape[0] > 1 or levels[-1].shape[1] > 1:
        levels.append(halve(halve(levels[-1], 0), 1).astype(np.float32))
    return levels


def packed(levels: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The levels flat, row by row, one after another: texels (N, 3) float32 and per level
    (offset, width, height) int32, as MeshLook.mip and mip_dims."""
    dims, offset = [], 0
    for lev in levels:
        dims.append((offset, lev.shape[1], lev.shape[0]))
        offset += lev.shape[0] * lev.shape[1]
    return np.concatenate([lev.reshape(-1, 3) for lev in levels]), np.array(dims, np.int32)


def face_texels(vertices_m: np.ndarray, faces: np.ndarray, uv: np.ndarray, texture_hw: tuple[int, int]) -> np.ndarray:
    """(F, 4) float32 per face: its unit normal (model frame; zero for a degenerate face) and its
    texels per metre at level 0, sqrt(area in texels² / area in m²) (0 where either area is 0:
    such a face is read at level 0)."""
    v = np.asarray(vertices_m, np.float64)[faces]
    t = np.asarray(uv, np.float64)[faces] * np.array([texture_hw[1], texture_hw[0]], np.float64)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area_m2 = 0.5 * np.linalg.norm(n, axis=1)
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area_tx = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    ok = area_m2 > 0.0
    out = np.zeros((len(faces), 4), np.float64)
    out[ok, :3] = n[ok] / (2.0 * area_m2[ok, None])
    out[ok, 3] = np.sqrt(area_tx[ok] / area_m2[ok])
    return out.astype(np.float32)


def set_mip(look: MeshLook, mesh=None) -> None:
    """Fill `look`'s mip fields on the current Warp device: the pyramid and face texel densities of
    `mesh` (an ObjectMesh with a texture), or, with no mesh, one-element placeholders and
    mip_levels 0 (plain bilinear lookups)."""
    if mesh is None or mesh.texture is None:
        look.mip = wp.zeros(1, dtype=wp.vec3)
        look.mip_dims = wp.zeros(1, dtype=wp.vec3i)
        look.face_texels = wp.zeros(1, dtype=wp.vec4)
        look.mip_levels = 0
        return
    levels = pyramid(mesh.texture)
    texels, dims = packed(levels)
    look.mip = wp.array(texels, dtype=wp.vec3)
    look.mip_dims = wp.array(dims, dtype=wp.vec3i)
    look.face_texels = wp.array(
        face_texels(mesh.vertices_m, mesh.faces, mesh.uv, mesh.texture.shape[:2]), dtype=wp.vec4
    )
    look.mip_levels = len(levels)
