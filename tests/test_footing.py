"""The footing term (perch_warp.footing, issue 17 (i)): the table in front of a candidate's footprint,
against a per-point loop, on constructed likeness maps, and its radius and map against their definitions."""

from __future__ import annotations

import math

import numpy as np

from perch_warp.camera import Camera
from perch_warp.demo import look_at_table
from perch_warp.footing import ARC_POINTS, FRONT_ARC_DEG, MARGIN_M, footing, footprint_radius_m, likeness_map
from perch_warp.score import grid_shape
from perch_warp.table import RestingPose, rot_z

KS, STRIDE = 11, 4


def _camera_table():
    camera = Camera(np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]), 320, 240)
    return camera, look_at_table(0.6, 50.0, 10.0)


def _loop_footing(table, camera, like, x, y, r):
    """One candidate, point by point: the arc's points projected, the nearest feature cell's likeness,
    the mean of the best ceil(n / 2) of the n seen."""
    cam = table.camera_center_table_m
    towards = math.atan2(cam[1] - y, cam[0] - x)
    seen = []
    for a in np.linspace(-math.radians(FRONT_ARC_DEG) / 2, math.radians(FRONT_ARC_DEG) / 2, ARC_POINTS):
        p = np.array([x + (r + MARGIN_M) * math.cos(towards + a), y + (r + MARGIN_M) * math.sin(towards + a), 0.0])
        pc = table.to_camera(p)
        if pc[2] <= 1e-6:
            continue
        u, v = camera.project(pc)
        gx, gy = round((u - KS // 2) / STRIDE), round((v - KS // 2) / STRIDE)
        if 0 <= gx < like.shape[1] and 0 <= gy < like.shape[0]:
            seen.append(float(like[gy, gx]))
    if not seen:
        return 0.0
    seen.sort(reverse=True)
    k = math.ceil(len(seen) / 2)
    return sum(seen[:k]) / k


def test_footing_equals_a_per_point_loop():
    camera, table = _camera_table()
    rows, cols = grid_shape(camera.width, camera.height, KS, STRIDE)
    rng = np.random.default_rng(3)
    like = rng.random((rows, cols)).astype(np.float32)
    # Candidates on the table in view, near the image's edges, and far beyond it (no arc point seen).
    x = np.concatenate([rng.uniform(-0.25, 0.25, 60), [3.0, -4.0]])
    y = np.concatenate([rng.uniform(-0.25, 0.25, 60), [0.0, 5.0]])
    got = footing(table, camera, like, x, y, 0.04, KS, STRIDE)
    ref = np.array([_loop_footing(table, camera, like, a, b, 0.04) for a, b in zip(x, y, strict=True)])
    assert np.allclose(got, ref, rtol=0, atol=1e-6)
    assert got[-1] == got[-2] == 0.0 and (got[:-2] > 0).sum() > 40
    assert np.all((got >= 0) & (got <= 1))


def test_footing_credits_a_place_whose_front_shows_the_table():
    """Likeness 1 on the image's lower half (the table near the camera), 0 on the upper half (say, a wall):
    a candidate near the camera stands on the table, one far up the image does not."""
    camera, table = _camera_table()
    rows, cols = grid_shape(camera.width, camera.height, KS, STRIDE)
    like = np.zeros((rows, cols), np.float32)
    like[rows // 2 :] = 1.0
    pts = table.ray_to_table(camera, np.array([[160.0, 200.0], [160.0, 30.0]]))
    near, far = footing(table, camera, like, pts[:, 0], pts[:, 1], 0.03, KS, STRIDE)
    assert near == 1.0 and far == 0.0


def test_likeness_map_and_footprint_radius():
    rng = np.random.default_rng(0)
    B = rng.normal(size=8)
    feats = np.stack([B + 0.01 * rng.normal(size=8) for _ in range(5)] + [-B, rng.normal(size=8)])
    labels = np.array([0, 0, 0, 0, 0, 1, 2])
    like = likeness_map(feats, labels, 1, 7)
    centroid = feats[:5].mean(axis=0)
    want = [max(0.0, f @ centroid / (np.linalg.norm(f) * np.linalg.norm(centroid))) for f in feats]
    assert np.allclose(like[0], want, atol=1e-6) and like[0, 5] == 0.0 and like[0, 0] > 0.99
    # A 0.10 x 0.06 x 0.04 box about its centre: upright, the half-diagonal of its top; turned about x
    # onto its long side (0.10 x 0.04 on the table) the same for any yaw.
    hull = np.array([[sx * 0.05, sy * 0.03, sz * 0.02] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    assert math.isclose(footprint_radius_m(hull, RestingPose.upright(hull)), math.hypot(0.05, 0.03))
    R_side = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    assert math.isclose(footprint_radius_m(hull, RestingPose.upright(hull, R_side)), math.hypot(0.05, 0.02))
    assert math.isclose(
        footprint_radius_m(hull, RestingPose.upright(hull, rot_z(0.7) @ R_side)), math.hypot(0.05, 0.02)
    )
