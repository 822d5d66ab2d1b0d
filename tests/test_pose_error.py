"""Pose errors against values worked out by hand (metres throughout)."""

import math

import numpy as np
import pytest

from perch_warp import pose_error as pe


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def cylinder_surface(radius: float = 0.03, height: float = 0.1, n_angle: int = 360, n_z: int = 11) -> np.ndarray:
    """Points on the lateral surface of a z-axis cylinder, every 1 degree."""
    a = np.radians(np.arange(n_angle) * 360.0 / n_angle)
    z = np.linspace(-height / 2, height / 2, n_z)
    A, Z = np.meshgrid(a, z)
    return np.stack([radius * np.cos(A).ravel(), radius * np.sin(A).ravel(), Z.ravel()], -1)


def test_identity_pose_has_zero_errors():
    pts = np.random.default_rng(1).normal(size=(500, 3)) * 0.05
    R, t = rot_z(0.4), np.array([0.1, -0.2, 0.7])
    assert pe.add(R, t, R, t, pts) == pytest.approx(0.0, abs=1e-12)
    assert pe.add_s(R, t, R, t, pts) == pytest.approx(0.0, abs=1e-12)


def test_pure_translation_gives_add_equal_to_distance_and_adds_at_most_that():
    pts = np.random.default_rng(2).uniform(-0.05, 0.05, size=(400, 3))
    R = rot_z(1.0)
    t_gt = np.array([0.0, 0.0, 0.8])
    d = np.array([0.012, -0.009, 0.0])  # |d| = 0.015 m
    assert pe.add(R, t_gt + d, R, t_gt, pts) == pytest.approx(0.015, abs=1e-12)
    adds = pe.add_s(R, t_gt + d, R, t_gt, pts)
    assert 0.0 < adds <= 0.015 + 1e-12


def test_adds_against_brute_force_nearest_neighbours():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.05, 0.05, size=(300, 3))
    R_e, t_e = rot_z(0.3), np.array([0.01, 0.02, 0.7])
    R_g, t_g = rot_z(-0.2), np.array([0.0, 0.0, 0.7])
    pe_ = pts @ R_e.T + t_e
    pg_ = pts @ R_g.T + t_g
    brute = np.linalg.norm(pg_[:, None, :] - pe_[None, :, :], axis=2).min(axis=1).mean()
    assert pe.adi(R_e, t_e, R_g, t_g, pts) == pytest.approx(brute, rel=1e-12)


def test_cylinder_rotated_about_its_axis_has_adds_zero_but_add_positive():
    r = 0.03
    pts = cylinder_surface(radius=r)
    t = np.array([0.0, 0.05, 0.6])
    theta = math.radians(30.0)  # a multiple of the 1-degree sampling: maps the points onto themselves
    assert pe.add_s(rot_z(theta), t, np.eye(3), t, pts) == pytest.approx(0.0, abs=1e-9)
    # Every lateral point moves along a chord of its circle.
    assert pe.add(rot_z(theta), t, np.eye(3), t, pts) == pytest.approx(2 * r * math.sin(theta / 2), rel=1e-9)
    # Off the sampling grid ADD-S stays below the half-step chord.
    assert pe.add_s(rot_z(math.radians(30.5)), t, np.eye(3), t, pts) < 2 * r * math.sin(math.radians(0.25)) + 1e-12


def test_box_flipped_by_its_symmetry_has_adds_zero():
    corners = np.array([[x, y, z] for x in (-0.02, 0.02) for y in (-0.03, 0.03) for z in (-0.05, 0.05)])
    t = np.array([0.0, 0.0, 0.5])
    assert pe.add_s(rot_z(math.pi), t, np.eye(3), t, corners) == pytest.approx(0.0, abs=1e-12)
    # ADD: the four corners at radius sqrt(0.02^2 + 0.03^2) each move by twice that.
    assert pe.add(rot_z(math.pi), t, np.eye(3), t, corners) == pytest.approx(2 * math.hypot(0.02, 0.03), rel=1e-12)


def test_subsample_is_deterministic_and_a_subset():
    pts = np.random.default_rng(4).normal(size=(20000, 3))
    a = pe.subsample_points(pts, 3000)
    b = pe.subsample_points(pts, 3000)
    assert a.shape == (3000, 3)
    np.testing.assert_array_equal(a, b)
    assert set(map(tuple, a)) <= set(map(tuple, pts))
    small = pts[:100]
    assert pe.subsample_points(small, 3000) is not None and len(pe.subsample_points(small, 3000)) == 100


def test_auc_of_a_known_error_list():
    # Each error e < 0.1 contributes (1 - e / 0.1) of full area; NaN/inf and e >= 0.1 contribute nothing.
    errors = [0.0, 0.05, 0.1, 0.2, float("nan"), float("inf"), 0.02]
    expected = 100 * (1.0 + 0.5 + 0 + 0 + 0 + 0 + 0.8) / 7
    assert pe.auc(errors) == pytest.approx(expected, abs=1e-12)


def test_auc_matches_numerical_integration_of_the_accuracy_curve():
    errors = np.random.default_rng(5).exponential(0.03, size=200)
    thr = np.linspace(0, 0.1, 200001)
    acc = pe.accuracy_curve(errors, thr)
    numeric = 100 * np.trapezoid(acc, thr) / 0.1
    assert pe.auc(errors) == pytest.approx(numeric, abs=0.01)


def test_auc_posecnn_reproduces_the_toolbox_right_end_rule():
    # One error of 5 cm: VOCap counts accuracy 1 from 0 on, the exact area is half.
    assert pe.auc_posecnn([0.05]) == pytest.approx(100.0)
    assert pe.auc([0.05]) == pytest.approx(50.0)
    # d = (0.02, 0.06), n = 2: 0.02 * 0.5 + 0.04 * 1 + 0.04 * 1 = 0.09 of 0.1.
    assert pe.auc_posecnn([0.06, 0.02]) == pytest.approx(90.0)
    assert pe.auc([0.06, 0.02]) == pytest.approx(60.0)
    assert pe.auc_posecnn([0.2, 0.3]) == 0.0


def test_accuracy_below_is_strict():
    assert pe.accuracy_below([0.019, 0.02, 0.021], 0.02) == pytest.approx(100 / 3)


def test_translation_and_yaw_errors():
    assert pe.translation_error([0.0, 0.03, 0.5], [0.04, 0.0, 0.5]) == pytest.approx(0.05)
    assert pe.yaw_error(math.radians(350), math.radians(10)) == pytest.approx(math.radians(20))
    assert pe.yaw_error(0.0, math.pi) == pytest.approx(math.pi)
    assert pe.yaw_error(-math.pi + 0.1, math.pi - 0.1) == pytest.approx(0.2)
    assert 0.0 <= pe.yaw_error(123.4, -56.7) <= math.pi
