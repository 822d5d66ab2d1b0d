"""The renderer back ends through their one interface (render.Renderer): BvhRenderer and RasterRenderer
give the same mask, and each one's silhouette() is exactly the feature points its render() mask covers,
which is what the pruned search's bound relies on."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.camera import Camera
from perch_warp.engine import Engine, EngineConfig
from perch_warp.render import (
    RENDERER_CLASSES,
    BvhRenderer,
    DeviceMesh,
    RasterRenderer,
    Renderer,
    make_renderer,
    point_layout,
    project_boxes,
)
from perch_warp.scene import label_texture, look_at_table, textured_box
from perch_warp.score import grid_boxes
from perch_warp.search_space import SearchSpace
from perch_warp.table import RestingPose, model_to_camera, pose_matrix

CAM = Camera(np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]), 320, 240)
TABLE = look_at_table(0.5, 45.0, 15.0)


@pytest.fixture(scope="module")
def dmesh() -> DeviceMesh:
    return DeviceMesh(textured_box((0.1, 0.06, 0.04), label_texture(np.random.default_rng(3))), DEVICE)


def _poses(dmesh: DeviceMesh, n: int = 12, seed: int = 1):
    """n model-to-camera poses of the mesh upright on the table within 12 cm (m), boxes in the image."""
    rng = np.random.default_rng(seed)
    rp = RestingPose.upright(dmesh.mesh.vertices_m)
    R, t = model_to_camera(TABLE, rp, rng.uniform(-0.12, 0.12, n), rng.uniform(-0.12, 0.12, n), rng.uniform(0, 7, n))
    boxes = project_boxes(CAM, dmesh.mesh.hull_points_m(), R, t)
    keep = (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
    return R[keep], t[keep], boxes[keep]


def _mask_at_points(mask: np.ndarray, boxes: np.ndarray, gboxes: np.ndarray, ks: int, stride: int) -> np.ndarray:
    """The rendered mask (flat, per box) at each feature point's pixel, 0 outside the box: kernel #2's reading."""
    out, off, half = [], 0, ks // 2
    for (x0, y0, w, h), (gx0, gy0, gw, gh) in zip(boxes, gboxes, strict=True):
        m = mask[off : off + w * h].reshape(h, w)
        off += w * h
        gy, gx = np.mgrid[gy0 : gy0 + gh, gx0 : gx0 + gw]
        u, v = half + stride * gx - x0, half + stride * gy - y0
        inside = (u >= 0) & (v >= 0) & (u < w) & (v < h)
        out.append(np.where(inside, m[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)], 0).ravel())
    return np.concatenate(out).astype(np.uint8)


def test_both_back_ends_are_renderers_with_one_interface(dmesh):
    assert set(RENDERER_CLASSES) == {"bvh", "raster"}
    for name, cls in RENDERER_CLASSES.items():
        r = make_renderer(name, dmesh)
        assert isinstance(r, Renderer) and isinstance(r, cls) and r.name == name and r.device == DEVICE
    assert not BvhRenderer(dmesh).cull_back_faces and RasterRenderer(dmesh).cull_back_faces  # a closed box


def test_bvh_and_raster_give_the_same_mask(dmesh):
    R, t, boxes = _poses(dmesh)
    a, b = BvhRenderer(dmesh).render(CAM, R, t, boxes), RasterRenderer(dmesh).render(CAM, R, t, boxes)
    ma, mb = a.mask.numpy(), b.mask.numpy()
    assert ma.sum() > 5_000 and np.array_equal(ma, mb)
    hit = ma > 0
    assert np.array_equal(a.rgb.numpy()[hit], b.rgb.numpy()[hit])


@pytest.mark.parametrize("name", ["bvh", "raster"])
@pytest.mark.parametrize("ks,stride", [(1, 1), (11, 4)])
def test_silhouette_is_the_render_mask_at_the_feature_points(dmesh, name, ks, stride):
    """ks = stride = 1: every pixel of the box is a feature point, so silhouette() is render()'s mask itself."""
    r = make_renderer(name, dmesh)
    R, t, boxes = _poses(dmesh, seed=2)
    gboxes = grid_boxes(boxes, ks, stride)
    hits = r.silhouette(CAM, R, t, point_layout(boxes, gboxes, ks, stride, DEVICE)).numpy()
    want = _mask_at_points(r.render(CAM, R, t, boxes).mask.numpy(), boxes, gboxes, ks, stride)
    assert hits.sum() > 100 and (hits == 0).sum() > 100
    assert np.array_equal(hits, want)


def test_the_engine_picks_a_renderer_per_search_without_changing_it(dmesh, random_weights):
    """--renderer auto picks per search: the engine's renderers are built once and left as they were."""
    engine = Engine(dmesh.mesh, random_weights, DEVICE, EngineConfig(refine=False))
    assert engine.renderer_for("raster") is engine.renderer_for("raster")
    before = engine.renderer
    R, t, _ = _poses(dmesh, 1, seed=3)
    image = engine.render(CAM, pose_matrix(R[0], t[0]))[0]
    image = np.round(np.clip(image + 0.3 * (image == 0), 0, 1) * 255).astype(np.uint8)
    space = SearchSpace((-0.02, 0.02), (-0.02, 0.02), 0.02, (0, 2 * math.pi), math.radians(90))
    res = engine.estimate(image, CAM, TABLE, RestingPose.upright(dmesh.mesh.vertices_m), space)
    assert res.info.renderer == "raster" and engine.renderer is before and before.name == "bvh"
