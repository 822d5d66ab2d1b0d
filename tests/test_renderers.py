"""The renderer back ends through their one interface (render.Renderer): BvhRenderer and RasterRenderer
give the same mask, and each one's silhouette() is exactly the feature points its render() mask covers,
which is what the pruned search's bound relies on."""

import dataclasses
import math

import numpy as np
import pytest
from _colour import srgb_exposed
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
from perch_warp.scene import label_texture, look_at_table, quad, textured_box
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


@pytest.mark.parametrize("name", ["bvh", "raster"])
@pytest.mark.parametrize("textured", [True, False])
def test_shading_scales_linear_light_by_lamberts_law(name, textured):
    """The score term shade: a flat square (one normal) tilted away from the camera, lit from several
    directions given in the model frame, against the unshaded render with the sRGB transfer written
    out: lin(c) x (1 - s + s max(0, n . l)), n the face's normal from its winding (model frame)."""
    tex = label_texture(np.random.default_rng(5), 128)
    corners = np.array([[-0.05, -0.05, 0.0], [0.05, -0.05, 0.0], [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0]])
    mesh = quad(corners, tex)
    if not textured:
        rng = np.random.default_rng(6)
        mesh = dataclasses.replace(mesh, uv=None, texture=None, vertex_colors=rng.uniform(0.1, 0.9, (4, 3)))
    dm = DeviceMesh(mesh, DEVICE)
    renderer = make_renderer(name, dm)
    v, f = np.asarray(mesh.vertices_m), np.asarray(mesh.faces)
    n = np.cross(v[f[0, 1]] - v[f[0, 0]], v[f[0, 2]] - v[f[0, 0]])
    n /= np.linalg.norm(n)
    # Model -> camera: the square 0.4 m ahead, its normal turned 30 degrees from the camera's axis, so
    # that the model and camera frames differ (a light taken in the wrong frame fails).
    a = math.radians(30.0)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    R = turn @ np.diag([1.0, -1.0, -1.0])
    t = np.array([0.0, 0.0, 0.4])
    if (R @ n)[2] > 0:  # seen from its back: turn it round so its normal faces the camera
        R = R @ np.diag([1.0, -1.0, -1.0])
    plain, mask = renderer.render_image(CAM, R, t)
    assert mask.sum() > 1000
    assert np.array_equal(renderer.render_image(CAM, R, t, dm.shading(n, 0.0))[0], plain)
    other = np.cross(n, [1.0, 0.0, 0.0])
    for light, s in [(n, 0.8), (n + other, 0.5), (-n, 0.7), (other, 1.0)]:
        lit, lit_mask = renderer.render_image(CAM, R, t, dm.shading(light, s))
        assert np.array_equal(lit_mask, mask)
        factor = 1.0 - s + s * max(0.0, float(n @ light) / np.linalg.norm(light))
        want = srgb_exposed(plain[mask].astype(np.float64), factor)
        np.testing.assert_allclose(lit[mask], want, atol=2e-5)
        assert np.array_equal(lit[~mask], plain[~mask])


def test_the_searchs_light_is_the_tables_normal_in_the_model_frame(random_weights):
    """ScoringService lights the render from above the table: the table's normal (camera frame) turned
    into the model frame by a candidate's pose, the same for every x, y and yaw."""
    rng = np.random.default_rng(2)
    mesh = textured_box((0.1, 0.06, 0.04), label_texture(rng))
    tilt = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # lying on a side: the model's +y up
    rp = RestingPose.upright(mesh.vertices_m, tilt)
    engine = Engine(mesh, random_weights, DEVICE, EngineConfig(score="shade=0.5"))
    photo = rng.integers(0, 256, (CAM.height, CAM.width, 3), dtype=np.uint8)
    service = engine.scoring(photo, CAM, TABLE, rp)
    sh = service.shading()
    assert sh.strength == 0.5
    R, _ = model_to_camera(TABLE, rp, [0.02, -0.05], [0.01, 0.03], [0.3, 2.0])
    for Rc in R:
        np.testing.assert_allclose(np.array(sh.light_m), Rc.T @ TABLE.R_t2c[:, 2], atol=1e-6)
    np.testing.assert_allclose(np.array(sh.light_m), [0.0, 1.0, 0.0], atol=1e-6)
