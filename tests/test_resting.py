"""Resting poses from the mesh (perch_warp.resting) against known answers, and the search over them."""

import math

import numpy as np
import pytest
import trimesh
from _device import DEVICE

from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.resting import _merge_faces, down_to_table, roll_family, stable_rests, upright_rest
from perch_warp.search_space import SearchSpace

DIMS = (0.10, 0.06, 0.03)  # box extents along model x, y, z (m): all different


def _box():
    b = trimesh.creation.box(DIMS)
    return np.asarray(b.vertices), np.asarray(b.faces)


def test_box_rests_on_each_of_its_six_faces_at_half_its_thickness():
    rests = stable_rests(*_box())
    downs = {tuple(np.round(r.down_m).astype(int)) for r in rests}
    # +z and -z down differ by a flip, not a yaw: a textured box shows another face, so both stay.
    assert downs == {(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)}
    for r in rests:
        axis = int(np.argmax(np.abs(r.down_m)))
        assert r.pose.z_m == pytest.approx(DIMS[axis] / 2, abs=1e-9)
        assert np.allclose(r.pose.R_rest @ r.down_m, [0, 0, -1], atol=1e-9)
        assert r.label == f"model {'+' if r.down_m[axis] > 0 else '-'}{'xyz'[axis]} down"
        assert r.roll_deg is None
    probs = [r.probability for r in rests]
    assert probs == sorted(probs, reverse=True) and sum(probs) == pytest.approx(1.0, abs=1e-6)
    # The largest faces (normal z) are the likeliest, the smallest (normal x) the least likely.
    assert [abs(round(r.down_m[2])) for r in rests[:2]] == [1, 1]
    assert [abs(round(r.down_m[0])) for r in rests[-2:]] == [1, 1]
    # Model -z down is exactly the upright pose (R = I), so the stable list contains today's default.
    (down_z,) = [r for r in rests if r.down_m[2] < -0.5]
    assert np.array_equal(down_z.pose.R_rest, np.eye(3))


def test_cube_faces_are_equally_likely():
    c = trimesh.creation.box((0.05, 0.05, 0.05))
    rests = stable_rests(c.vertices, c.faces)
    assert len(rests) == 6
    assert np.allclose([r.probability for r in rests], 1 / 6, atol=1e-6)


def test_cylinder_stands_on_either_end_or_rolls_on_its_side():
    r_m, h_m = 0.03, 0.10
    cyl = trimesh.creation.cylinder(r_m, h_m, sections=48)
    rests = stable_rests(cyl.vertices, cyl.faces, roll_step_deg=30.0)
    ends = [r for r in rests if r.roll_deg is None]
    rolls = [r for r in rests if r.roll_deg is not None]
    assert sorted(r.label for r in ends) == ["model +z down", "model -z down"]
    assert all(r.pose.z_m == pytest.approx(h_m / 2, abs=1e-9) for r in ends)
    assert [r.roll_deg for r in rolls] == [30.0 * k for k in range(12)]
    for r in rolls:
        assert np.allclose(r.axis_m, [0, 0, 1], atol=1e-6)
        # The lowest vertex of a 48-gon lies between the apothem and the radius below the axis.
        assert r_m * math.cos(math.pi / 48) - 1e-9 <= r.pose.z_m <= r_m + 1e-9
        assert np.allclose(r.pose.R_rest @ r.axis_m, [1, 0, 0], atol=1e-9)  # the axis lies level, along x
        assert np.allclose(r.pose.R_rest @ r.down_m, [0, 0, -1], atol=1e-9)
        assert abs(r.down_m[2]) < 1e-9
    assert "roll 0 deg about model +z (model +x down at 0)" in rolls[0].label
    assert np.allclose(rolls[3].down_m, [0, 1, 0], atol=1e-9)  # roll 90: model +y down
    assert len(stable_rests(cyl.vertices, cyl.faces, roll_step_deg=45.0)) == 2 + 8


def test_a_box_never_rolls_and_near_parallel_faces_merge():
    # A box's four sides around an axis are four 90-degree-apart facets, not a curved side.
    assert roll_family(np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])) is None
    two_deg = np.radians(2.0)
    downs = np.array([[0, 0, -1.0], [np.sin(two_deg), 0, -np.cos(two_deg)], [1.0, 0, 0]])
    merged = _merge_faces(downs, np.array([0.5, 0.3, 0.2]))
    assert len(merged) == 2 and merged[0][1] == pytest.approx(0.8) and np.allclose(merged[0][0], [0, 0, -1])


def test_rotations_take_down_to_the_table_and_bad_input_fails_in_one_line():
    rng = np.random.default_rng(0)
    for d in [*rng.normal(size=(20, 3)), np.array([0, 0, 1.0]), np.array([0, 0, -1.0])]:
        R = down_to_table(d)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
        assert np.allclose(R @ (d / np.linalg.norm(d)), [0, 0, -1], atol=1e-12)
    flat = trimesh.creation.box((0.1, 0.1, 0.0))
    with pytest.raises(PerchError, match="flat"):
        stable_rests(flat.vertices, flat.faces)
    with pytest.raises(PerchError, match="--roll-step"):
        stable_rests(*_box(), roll_step_deg=0.0)


@pytest.fixture(scope="module")
def lying():
    """The demo scene with the box lying on its model +x face (0.11 m along x: 0.055 m high)."""
    return demo_scene(seed=1, target_down=np.array([1.0, 0.0, 0.0]))


def _space(sc, half=0.02, yaw_deg=30.0):
    gx, gy, _ = sc.truth_xy_yaw
    cx, cy = round(gx / 0.01) * 0.01, round(gy / 0.01) * 0.01
    return SearchSpace((cx - half, cx + half), (cy - half, cy + half), 0.01, (0, 2 * math.pi), math.radians(yaw_deg))


def _poses(result, rest=True):
    return [(c.x_m, c.y_m, c.yaw_rad) + ((c.rest,) if rest else ()) for c in result.top_k]


def test_stable_search_finds_the_lying_box_and_pruned_equals_exhaustive(lying, caffe_weights):
    rests = stable_rests(lying.mesh.vertices_m, lying.mesh.faces)
    space = _space(lying)
    args = (lying.image, lying.camera, lying.table, rests, space)
    res = {
        s: Engine(lying.mesh, caffe_weights, DEVICE, EngineConfig(search=s, refine=False)).estimate(*args)
        for s in ("exhaustive", "pruned")
    }
    ex, pr = res["exhaustive"], res["pruned"]
    assert ex.resting.label == "model +x down" and ex.resting.z_m == pytest.approx(0.055)
    gx, gy, gyaw = lying.truth_xy_yaw
    assert abs(ex.x_m - gx) <= 0.01 and abs(ex.y_m - gy) <= 0.01
    assert abs(math.degrees((ex.yaw_rad - gyaw + math.pi) % (2 * math.pi) - math.pi)) <= 30.0
    assert ex.n_candidates == len(space) * len(rests) == ex.info.evaluated
    assert [(c.x_m, c.y_m, c.yaw_rad, c.rest) for c in pr.top_k] == [
        (c.x_m, c.y_m, c.yaw_rad, c.rest) for c in ex.top_k
    ]
    assert np.allclose([c.score for c in pr.top_k], [c.score for c in ex.top_k], rtol=0, atol=1e-6)
    assert pr.resting.index == ex.resting.index
    # Each pose's best grid score is its own search's: the winner's is the answer's.
    assert max(ex.resting.best_scores) == pytest.approx(ex.score, abs=1e-6)


def test_pruned_shares_its_bar_across_poses_and_refines_exactly_like_exhaustive(lying, caffe_weights):
    rests = (
        stable_rests(lying.mesh.vertices_m, lying.mesh.faces)[:3]
        + stable_rests(lying.mesh.vertices_m, lying.mesh.faces)[4:5]
    )
    space = _space(lying, half=0.01, yaw_deg=45.0)
    args = (lying.image, lying.camera, lying.table, rests, space)
    cfg = {"refine_peaks": 2, "top_k": 3}
    ex = Engine(lying.mesh, caffe_weights, DEVICE, EngineConfig(search="exhaustive", **cfg)).estimate(*args)
    pr = Engine(lying.mesh, caffe_weights, DEVICE, EngineConfig(search="pruned", **cfg)).estimate(*args)
    assert [(c.x_m, c.y_m, c.yaw_rad, c.rest) for c in pr.top_k] == [
        (c.x_m, c.y_m, c.yaw_rad, c.rest) for c in ex.top_k
    ]
    assert pr.score == pytest.approx(ex.score, abs=1e-6) and pr.resting.label == "model +x down"


def test_one_pose_in_a_list_is_the_single_pose_search(caffe_weights):
    sc = demo_scene(seed=1)
    space = _space(sc, half=0.01, yaw_deg=45.0)
    engine = Engine(sc.mesh, caffe_weights, DEVICE, EngineConfig(search="pruned"))
    a = engine.estimate(sc.image, sc.camera, sc.table, sc.resting, space)
    b = engine.estimate(sc.image, sc.camera, sc.table, [upright_rest(sc.mesh.vertices_m)], space)
    assert [(c.x_m, c.y_m, c.yaw_rad, c.score) for c in a.top_k] == [
        (c.x_m, c.y_m, c.yaw_rad, c.score) for c in b.top_k
    ]
    assert np.array_equal(a.T_m2c, b.T_m2c) and a.resting is None and b.resting.index == 0
