"""Mip-mapped texture lookups (score term texture=mip, perch_warp/mipmap.py, kernels/render.py): the
pyramid against plain NumPy averages, the face texel densities of a known quad, and both renderers'
pixels against a NumPy trilinear lookup at the level the pixel's footprint asks for."""

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.camera import Camera
from perch_warp.errors import PerchError
from perch_warp.mesh import ObjectMesh
from perch_warp.mipmap import face_texels, halve, packed, pyramid
from perch_warp.render import DeviceMesh, make_renderer
from perch_warp.score_terms import parse_score

SIDE_M = 0.1
CAM = Camera(np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]]), 160, 120)


def _quad(texture: np.ndarray) -> ObjectMesh:
    """A SIDE_M square in the model's z = 0 plane, normal +z, uv = (x / side + 0.5, y / side + 0.5)."""
    h = SIDE_M / 2
    V = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    uv = (V[:, :2] / SIDE_M + 0.5).astype(np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return ObjectMesh(V, F, uv, texture.astype(np.float32))


def _bilinear(level: np.ndarray, u: float, v: float) -> np.ndarray:
    """sample_texture's convention in NumPy: row 0 at v = 0, texel centres at (i + 0.5) / n, wrapped."""
    h, w = level.shape[:2]
    x, y = (u % 1.0) * w - 0.5, (v % 1.0) * h - 0.5
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - x0, y - y0
    x0, y0 = x0 % w, y0 % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    top = level[y0, x0] * (1 - fx) + level[y0, x1] * fx
    bot = level[y1, x0] * (1 - fx) + level[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def test_pyramid_levels_are_plain_averages():
    rng = np.random.default_rng(0)
    tex = rng.random((16, 8, 3)).astype(np.float32)
    levels = pyramid(tex)
    assert [lv.shape[:2] for lv in levels] == [(16, 8), (8, 4), (4, 2), (2, 1), (1, 1)]
    np.testing.assert_allclose(levels[1], tex.reshape(8, 2, 4, 2, 3).mean(axis=(1, 3)), rtol=1e-6)
    np.testing.assert_allclose(levels[-1][0, 0], tex.reshape(-1, 3).mean(0), rtol=1e-5)
    flat, dims = packed(levels)
    assert dims.tolist()[:2] == [[0, 8, 16], [128, 4, 8]] and len(flat) == sum(
        lv.shape[0] * lv.shape[1] for lv in levels
    )
    np.testing.assert_array_equal(flat[128 : 128 + 32].reshape(8, 4, 3), levels[1])


def test_odd_sides_keep_the_mean():
    a = np.arange(5.0)[:, None] * np.ones((1, 3))
    h = halve(a, 0)  # two samples, each over 2.5 old ones: (0 + 1 + 0.5 * 2) / 2.5, (0.5 * 2 + 3 + 4) / 2.5
    np.testing.assert_allclose(h[:, 0], [0.8, 3.2])
    tex = np.random.default_rng(1).random((7, 5, 3))
    for lv in pyramid(tex):
        np.testing.assert_allclose(lv.reshape(-1, 3).mean(0), tex.reshape(-1, 3).mean(0), rtol=1e-5)


def test_face_texels_of_a_known_quad():
    m = _quad(np.zeros((64, 32, 3)))
    ft = face_texels(m.vertices_m, m.faces, m.uv, (64, 32))
    np.testing.assert_allclose(ft[:, :3], [[0, 0, 1], [0, 0, 1]], atol=1e-6)
    # 64 x 32 texels over 0.1 m x 0.1 m: sqrt(2048 / 0.01) texels per metre
    np.testing.assert_allclose(ft[:, 3], np.sqrt(64 * 32 / SIDE_M**2), rtol=1e-5)


def _reference(tex: np.ndarray, depth_m: float, pixels) -> np.ndarray:
    """NumPy colour of each pixel (u, v) of the quad facing the camera at depth_m: the hit's uv, the level
    log2(texels across the footprint depth / f / sqrt(cos)), trilinear between the two levels around it."""
    levels = pyramid(tex)
    fx = CAM.K[0, 0]
    per_m = np.sqrt(tex.shape[0] * tex.shape[1] / SIDE_M**2)
    out = []
    for u, v in pixels:
        ray = np.array([(u - CAM.K[0, 2]) / fx, (v - CAM.K[1, 2]) / fx, 1.0])
        x, y = ray[0] * depth_m, ray[1] * depth_m
        cos_i = 1.0 / np.linalg.norm(ray)
        lod = min(np.log2(max(per_m * depth_m / fx / np.sqrt(cos_i), 1.0)), len(levels) - 1)
        l0 = int(np.floor(lod))
        a = _bilinear(levels[l0], x / SIDE_M + 0.5, y / SIDE_M + 0.5)
        if lod > l0:
            a = a * (1 - (lod - l0)) + _bilinear(levels[l0 + 1], x / SIDE_M + 0.5, y / SIDE_M + 0.5) * (lod - l0)
        out.append(a)
    return np.array(out)


@pytest.mark.parametrize("method", ["bvh", "raster"])
def test_render_reads_the_level_of_the_pixel_footprint(method):
    rng = np.random.default_rng(2)
    tex = rng.random((256, 256, 3))
    depth = 0.5  # 300 px focal length: 1.67 mm per pixel, 2560 texels per metre: about 4.3 texels per pixel
    mip = make_renderer(method, DeviceMesh(_quad(tex), DEVICE, "mip"))
    plain = make_renderer(method, DeviceMesh(_quad(tex), DEVICE, "bilinear"))
    R, t = np.eye(3), np.array([0.0, 0.0, depth])
    rgb, mask = mip.render_image(CAM, R, t)
    rgb_plain, mask_plain = plain.render_image(CAM, R, t)
    np.testing.assert_array_equal(mask, mask_plain)  # only colours change
    pixels = [(80, 60), (50, 40), (100, 75), (61, 83)]
    assert all(mask[v, u] for u, v in pixels)
    got = np.array([rgb[v, u] for u, v in pixels])
    np.testing.assert_allclose(got, _reference(tex, depth, pixels), atol=2e-5)
    # The pre-averaged render varies far less than the one-texel lookups (aliasing), around the same mean.
    inner = mask.copy()
    inner[:, :40] = inner[:, 120:] = False
    assert rgb[inner].std(0).max() < 0.5 * rgb_plain[inner].std(0).min()
    np.testing.assert_allclose(rgb[inner].mean(0), rgb_plain[inner].mean(0), atol=0.02)


def test_both_renderers_agree_with_mip():
    tex = np.random.default_rng(4).random((128, 64, 3))
    a = make_renderer("bvh", DeviceMesh(_quad(tex), DEVICE, "mip"))
    b = make_renderer("raster", DeviceMesh(_quad(tex), DEVICE, "mip"))
    c, s = np.cos(0.6), np.sin(0.6)
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])  # tilted: the footprint grows with the incidence
    rgb_a, mask_a = a.render_image(CAM, R, np.array([0.01, 0.0, 0.4]))
    rgb_b, mask_b = b.render_image(CAM, R, np.array([0.01, 0.0, 0.4]))
    both = mask_a & mask_b
    assert both.sum() > 0.99 * max(mask_a.sum(), mask_b.sum()) > 1000
    np.testing.assert_allclose(rgb_a[both], rgb_b[both], atol=1e-4)


def test_texture_term_parses_and_refuses_unknown_filters():
    name, terms = parse_score("shift=1,texture=mip")
    assert terms.texture == "mip" and terms.shift == 1 and "texture=mip" in name
    assert parse_score("grid-tolerant")[1].texture == "bilinear"
    with pytest.raises(PerchError, match="texture"):
        parse_score("texture=trilinear")
    with pytest.raises(PerchError, match="texture"):
        DeviceMesh(_quad(np.zeros((4, 4, 3))), DEVICE, "nearest")
