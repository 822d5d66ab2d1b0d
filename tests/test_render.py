"""Kernel #1 against independent geometry: projections of mesh vertices and known face colours,
in both its forms (bvh: Warp's mesh query per ray; raster: per triangle, kernels/raster.py)."""

import math

import numpy as np
import pytest
from _device import DEVICE
from matplotlib.path import Path as MplPath
from scipy.spatial import ConvexHull

from perch_warp.camera import Camera
from perch_warp.render import BoxProjector, mesh_renderer, project_boxes
from perch_warp.scene import look_at_table, striped_cylinder, textured_box
from perch_warp.table import RestingPose, model_to_camera, rot_z

CAM = Camera(np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]), 320, 240)
TABLE = look_at_table(0.5, 45.0, 15.0)
TILE_COLORS = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1], [1, 0, 1]], np.float32)


def _tile_texture(size: int = 96) -> np.ndarray:
    """A 3 x 2 atlas, each tile one solid colour (image rows top first, as in a PNG)."""
    tex = np.zeros((size, size, 3), np.float32)
    th, tw = size // 2, size // 3
    for k, c in enumerate(TILE_COLORS):
        r, col = divmod(k, 3)
        tex[r * th : (r + 1) * th, col * tw : (col + 1) * tw] = c
    return tex[::-1]  # textured_box flips rows back: tile k sits at atlas row r = k // 3 from v = 0


def _pose(mesh, x=0.01, y=-0.02, yaw_deg=30.0):
    rp = RestingPose.upright(mesh.vertices_m)
    R, t = model_to_camera(TABLE, rp, x, y, math.radians(yaw_deg))
    return R[0], t[0]


@pytest.fixture(scope="module")
def box():
    return textured_box((0.1, 0.06, 0.04), _tile_texture())


METHODS = pytest.mark.parametrize("method", ["bvh", "raster"])


@METHODS
def test_mask_matches_projected_vertex_hull(box, method):
    R, t = _pose(box)
    rgb, mask = mesh_renderer(box, DEVICE, method).render_image(CAM, R, t)
    uv = CAM.project(box.vertices_m @ R.T + t)
    hull = uv[ConvexHull(uv).vertices]
    vv, uu = np.mgrid[0 : CAM.height, 0 : CAM.width]
    inside = MplPath(hull).contains_points(np.stack([uu.ravel(), vv.ravel()], -1)).reshape(mask.shape)
    iou = (inside & mask).sum() / (inside | mask).sum()
    assert iou > 0.97
    # Disagreements may only sit on the outline (within a pixel of the hull's edge).
    grown = MplPath(hull).contains_points(np.stack([uu.ravel(), vv.ravel()], -1), radius=2.0).reshape(mask.shape)
    shrunk = MplPath(hull).contains_points(np.stack([uu.ravel(), vv.ravel()], -1), radius=-2.0).reshape(mask.shape)
    assert not (mask & ~(inside | grown)).any() and not (shrunk & inside & ~mask).any()


@METHODS
def test_face_colours_come_from_their_texture_tiles(box, method):
    R, t = _pose(box)
    rgb, mask = mesh_renderer(box, DEVICE, method).render_image(CAM, R, t)
    checked = 0
    for k in range(6):
        quad = box.vertices_m[4 * k : 4 * k + 4] @ R.T + t
        centre = quad.mean(0)
        outward = centre - t  # the box is centred on its model origin
        if np.dot(outward, centre) >= 0:
            continue  # faces away from the camera
        u, v = np.round(CAM.project(centre)).astype(int)
        assert mask[v, u]
        assert np.allclose(rgb[v, u], TILE_COLORS[k], atol=1e-3), f"face {k}"
        checked += 1
    assert checked >= 2


@METHODS
def test_vertex_colours_are_interpolated(method):
    cyl = striped_cylinder(0.03, 0.08, np.random.default_rng(0))
    cyl = type(cyl)(cyl.vertices_m, cyl.faces, None, None, np.tile([[0.2, 0.5, 0.7]], (len(cyl.vertices_m), 1)))
    R, t = _pose(cyl)
    rgb, mask = mesh_renderer(cyl, DEVICE, method).render_image(CAM, R, t)
    assert mask.sum() > 200
    assert np.allclose(rgb[mask], [0.2, 0.5, 0.7], atol=1e-5)


@METHODS
def test_batched_boxes_equal_single_renders(box, method):
    r = mesh_renderer(box, DEVICE, method)
    rp = RestingPose.upright(box.vertices_m)
    R, t = model_to_camera(
        TABLE, rp, np.array([0.0, 0.03, -0.05]), np.array([0.0, 0.02, 0.01]), np.radians([0, 50, 200])
    )
    boxes = project_boxes(CAM, box.hull_points_m(), R, t)
    batch = r.render(CAM, R, t, boxes)
    rgb, mask = batch.rgb.numpy(), batch.mask.numpy()
    off = batch.pix_off.numpy()
    for i in range(3):
        full_rgb, full_mask = r.render_image(CAM, R[i], t[i])
        x0, y0, w, h = boxes[i]
        assert full_mask.sum() == mask[off[i] : off[i + 1]].sum()  # the box holds the whole silhouette
        assert np.array_equal(full_mask[y0 : y0 + h, x0 : x0 + w].ravel(), mask[off[i] : off[i + 1]].astype(bool))
        assert np.allclose(full_rgb[y0 : y0 + h, x0 : x0 + w].reshape(-1, 3), rgb[off[i] : off[i + 1]])


def test_boxes_flag_candidates_outside_or_behind():
    hull = np.array([[-0.01, -0.01, 0], [0.01, 0.01, 0.02]])
    R = np.repeat(np.eye(3)[None], 4, 0)
    t = np.array([[0.0, 0.0, 0.5], [5.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.27, 0.0, 0.5]])
    boxes = project_boxes(CAM, hull, R, t)
    assert boxes[0, 2] > 0 and boxes[0, 3] > 0
    assert tuple(boxes[1]) == (0, 0, 0, 0)
    assert boxes[2, 2] == -1
    # Overlapping the right edge: the box keeps the part beyond the image.
    assert boxes[3, 0] < CAM.width <= boxes[3, 0] + boxes[3, 2] - 1


def test_device_boxes_equal_numpy_boxes(box):
    """The engine's box kernel against project_boxes, integer for integer: table poses over and
    beyond the image, random 3-D rotations, and candidates behind or too close to the camera."""
    rng = np.random.default_rng(5)
    hull = striped_cylinder(0.03, 0.08, np.random.default_rng(0)).hull_points_m()
    rp = RestingPose.upright(box.vertices_m)
    n = 3000
    R_tab, t_tab = model_to_camera(
        TABLE, rp, rng.uniform(-0.6, 0.6, n), rng.uniform(-0.6, 0.6, n), rng.uniform(0, 2 * math.pi, n)
    )
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R_rand = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    t_rand = rng.uniform([-0.4, -0.3, -0.1], [0.4, 0.3, 0.8], (n, 3))
    R = np.concatenate([R_tab, R_rand, rot_z(rng.uniform(0, 6, 4))])
    # The last four: wholly in view, off to the side, behind, and straddling the near limit.
    t = np.concatenate([t_tab, t_rand, [[0.0, 0.0, 0.5], [5.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.05]]])
    for hull_m in (hull, box.hull_points_m()):
        ref = project_boxes(CAM, hull_m, R, t)
        got = BoxProjector(hull_m, DEVICE)(CAM, R, t)
        assert got.dtype == np.int32 and got.shape == ref.shape
        assert np.array_equal(got, ref)
        inside, empty, behind = (ref[:, 2] > 0).sum(), (ref[:, 2] == 0).sum(), (ref[:, 2] < 0).sum()
        assert min(inside, empty, behind) > 50  # every branch is exercised
    assert BoxProjector(hull, DEVICE)(CAM, R[:0], t[:0]).shape == (0, 4)
