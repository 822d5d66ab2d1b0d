import math

import numpy as np
import pytest

from perch_warp.camera import Camera
from perch_warp.errors import PerchError
from perch_warp.scene import look_at_table
from perch_warp.table import RestingPose, Table, decompose_on_table, model_to_camera, rot_z


def _random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_decompose_then_compose_gives_back_the_pose():
    rng = np.random.default_rng(0)
    table = look_at_table(0.7, 40.0, 10.0)
    for _ in range(20):
        R = _random_rotation(rng)
        t = np.array([0.05, -0.1, 0.6]) + rng.normal(0, 0.05, 3)
        resting, x, y, yaw = decompose_on_table(table, R, t)
        R2, t2 = model_to_camera(table, resting, x, y, yaw)
        assert np.allclose(R2[0], R, atol=1e-9)
        assert np.allclose(t2[0], t, atol=1e-9)


def test_upright_object_has_identity_rest_and_its_yaw():
    table = look_at_table(0.7, 40.0, 10.0)
    resting = RestingPose(np.eye(3), 0.03)
    R, t = model_to_camera(table, resting, 0.02, -0.04, math.radians(123))
    rp, x, y, yaw = decompose_on_table(table, R[0], t[0])
    assert np.allclose(rp.R_rest, np.eye(3), atol=1e-9)
    assert (x, y) == pytest.approx((0.02, -0.04))
    assert math.degrees(yaw) == pytest.approx(123)
    assert rp.z_m == pytest.approx(0.03)


def test_upright_rest_puts_lowest_vertex_on_table():
    V = np.array([[0, 0, -0.07], [0.1, 0, 0.05], [0, 0.1, 0.02]])
    rp = RestingPose.upright(V)
    _, t = rp.model_to_table(0.0, 0.0, 1.0)
    z = (V @ rot_z(1.0).T + t[0])[:, 2]
    assert z.min() == pytest.approx(0.0)


def test_ray_to_table_inverts_projection():
    table = look_at_table(0.8, 35.0, -20.0)
    cam = Camera(np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.0]]), 640, 480)
    pts = np.array([[0.1, 0.05, 0.0], [-0.2, 0.1, 0.0], [0.0, 0.0, 0.0]])
    uv = cam.project(table.to_camera(pts))
    assert np.allclose(table.ray_to_table(cam, uv), pts, atol=1e-9)


def test_table_behind_camera_is_refused():
    with pytest.raises(PerchError, match="behind the camera"):
        Table(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, -0.5]))


def test_non_rotation_is_refused():
    with pytest.raises(PerchError, match="not a rotation"):
        Table.from_bop([1, 0, 0, 0, 2, 0, 0, 0, 1], [0, 0, 1000])
