"""Refinement below the grid: the cell's fine grid, then the engine on a photographed scene."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.refine import cell_space, fine_steps
from perch_warp.score_terms import parse_score
from perch_warp.search_space import FULL_CIRCLE, SearchSpace

# The score the refinement below the grid uses: the default's terms less the grid's shift.
REFINE_SCORE = parse_score(EngineConfig().score)[1].below_grid().spec()


def _ang(a, b):
    return np.abs((np.asarray(a) - b + math.pi) % (2 * math.pi) - math.pi)


def test_fine_steps_divide_the_grid_step_and_meet_the_target():
    assert fine_steps(0.01, 0.002) == pytest.approx((0.002, 5))
    assert fine_steps(0.02, 0.002) == pytest.approx((0.002, 10))
    step, n = fine_steps(0.1, math.radians(1.0))  # 0.1 rad = 5.73 deg: six steps of 0.955 deg
    assert n == 6 and step == pytest.approx(0.1 / 6) and step <= math.radians(1.0)
    assert fine_steps(0.001, 0.002) == pytest.approx((0.001, 1))  # the grid is already fine enough
    with pytest.raises(PerchError, match="positive"):
        fine_steps(0.01, 0.0)


def test_cell_is_one_grid_step_either_side_and_contains_the_grid_pose():
    space = SearchSpace((-0.1, 0.1), (-0.2, 0.0), 0.01, FULL_CIRCLE, math.radians(5))
    cell = cell_space(space, 0.03, -0.12, math.radians(40), 0.002, math.radians(1))
    xs, ys, yaws = cell.axes()
    assert len(xs) == len(ys) == 11 and len(yaws) == 11
    assert xs[0] == pytest.approx(0.02) and xs[-1] == pytest.approx(0.04)
    assert np.min(np.abs(xs - 0.03)) < 1e-12 and np.min(np.abs(ys + 0.12)) < 1e-12
    assert np.min(_ang(yaws, math.radians(40))) < 1e-12
    assert np.allclose(np.diff(yaws), math.radians(1)) and cell.xy_step_m == pytest.approx(0.002)
    # A wider window: two grid steps either side, the same fine steps.
    wide = cell_space(space, 0.03, -0.12, math.radians(40), 0.002, math.radians(1), cells=2)
    assert [len(a) for a in wide.axes()] == [21, 21, 21] and wide.x_range_m == pytest.approx((0.01, 0.05))
    with pytest.raises(PerchError, match="at least 1 grid step"):
        cell_space(space, 0.03, -0.12, 0.0, 0.002, 0.01, cells=0)
    # Across 0 degrees the cell keeps going (yaws below 0 are the same poses as below 360).
    cell0 = cell_space(space, 0.03, -0.12, 0.0, 0.002, math.radians(1))
    assert cell0.axes()[2][0] == pytest.approx(math.radians(-5))


def test_cell_is_cut_to_the_searched_region():
    space = SearchSpace((-0.1, 0.1), (-0.2, 0.0), 0.01, (0.0, math.radians(90)), math.radians(5))
    cell = cell_space(space, 0.1, -0.2, 0.0, 0.002, math.radians(1))
    xs, ys, yaws = cell.axes()
    assert xs[0] == pytest.approx(0.09) and xs[-1] == pytest.approx(0.1)
    assert ys[0] == pytest.approx(-0.2) and ys[-1] == pytest.approx(-0.19)
    assert yaws[0] == pytest.approx(0.0) and yaws[-1] == pytest.approx(math.radians(5))


@pytest.fixture(scope="module")
def scene():
    return demo_scene(seed=1)


def test_engine_refines_the_photographed_box_below_its_grid(scene, caffe_weights):
    """The demo's box (lit, shadowed, noisy photo) at an off-grid pose: a 1 cm / 30° grid finds it
    within a step; the refinement returns the best pose of an exhaustive 2 mm / 1° search of that
    grid pose's cell, within 2 mm and 1° of the truth."""
    gx, gy, gyaw = scene.truth_xy_yaw
    cx, cy = round(gx / 0.01) * 0.01 + 0.01, round(gy / 0.01) * 0.01 - 0.01
    space = SearchSpace((cx - 0.03, cx + 0.03), (cy - 0.03, cy + 0.03), 0.01, FULL_CIRCLE, math.radians(30))
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    grid = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(refine=False)).estimate(*args)
    # Yaw target 3 deg keeps the test's cell small (11 x 11 x 21 poses); x/y at the default 2 mm.
    cfg = EngineConfig(refine_yaw_rad=math.radians(3.0))
    fine = Engine(scene.mesh, caffe_weights, DEVICE, cfg).estimate(*args)
    assert math.degrees(_ang(grid.yaw_rad, gyaw)) > 3.0  # so the test shows the refinement at work
    assert abs(fine.x_m - gx) <= 0.002 and abs(fine.y_m - gy) <= 0.002
    assert math.degrees(_ang(fine.yaw_rad, gyaw)) <= 3.0 and 0 <= fine.yaw_rad < 2 * math.pi
    ref = fine.info.extra["refine"]
    assert fine.score > grid.score and ref["score_gain"] == pytest.approx(fine.score - grid.score)
    assert (ref["from"]["x_m"], ref["from"]["y_m"]) == (grid.x_m, grid.y_m)

    # The independent reference: every pose of the cell scored by the exhaustive search.
    cell = cell_space(space, grid.x_m, grid.y_m, grid.yaw_rad, 0.002, math.radians(3.0))
    # The refinement scores with the default score's terms less its grid shift.
    ex_cfg = EngineConfig(search="exhaustive", refine=False, top_k=1, score=REFINE_SCORE)
    ex = Engine(scene.mesh, caffe_weights, DEVICE, ex_cfg).estimate(
        scene.image, scene.camera, scene.table, scene.resting, cell
    )
    assert ref["candidates"] == len(cell) == ex.n_candidates
    assert (fine.x_m, fine.y_m) == pytest.approx((ex.x_m, ex.y_m), abs=1e-12)
    assert _ang(fine.yaw_rad, ex.yaw_rad) < 1e-9 and fine.score == pytest.approx(ex.score, abs=1e-6)
    # The grid search itself is unchanged, and its counters do not include the refinement's.
    assert (fine.n_scored, fine.info.rays) == (grid.n_scored, grid.info.rays)
    assert ref["rays"] > 0 and "refine" in fine.timings_s
    # The runners-up stay grid poses, below the refined best.
    assert all(c.score <= fine.score for c in fine.top_k[1:])


def test_grid_shift_tolerance_scores_the_grid_and_not_the_refinement(scene, caffe_weights):
    """score_terms' shift: on the grid every candidate scores at least the plain score (the undisplaced
    comparison is one of the shifts) and at most its best displacement; the refinement below the grid
    scores undisplaced, so the answer's score is the plain score of the answer's pose."""
    gx, gy, _ = scene.truth_xy_yaw
    cx, cy = round(gx / 0.01) * 0.01, round(gy / 0.01) * 0.01
    space = SearchSpace((cx - 0.02, cx + 0.02), (cy - 0.02, cy + 0.02), 0.01, FULL_CIRCLE, math.radians(30))
    args = (scene.image, scene.camera, scene.table, scene.resting)
    poses = space.at(np.arange(len(space)))
    plain = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(refine=False, score="thesis"))
    shifted = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(refine=False, score="shift=1"))
    s0, s1 = plain.score(*args, *poses), shifted.score(*args, *poses)
    live = np.isfinite(s0)
    assert np.array_equal(live, np.isfinite(s1)) and live.sum() > 20
    assert np.all(s1[live] >= s0[live]) and np.any(s1[live] > s0[live] + 1e-3)

    cfg = EngineConfig(score="shift=1", refine_yaw_rad=math.radians(3.0))
    fine = Engine(scene.mesh, caffe_weights, DEVICE, cfg).estimate(*args, space)
    ref = fine.info.extra["refine"]
    best = int(np.nanargmax(np.where(live, s1, -np.inf)))
    assert (ref["from"]["x_m"], ref["from"]["y_m"]) == pytest.approx((poses[0][best], poses[1][best]), abs=1e-12)
    assert ref["from"]["score"] == pytest.approx(s1[best], abs=1e-9)
    again = plain.score(*args, np.array([fine.x_m]), np.array([fine.y_m]), np.array([fine.yaw_rad]))
    assert fine.score == pytest.approx(float(again[0]), abs=1e-6)
    assert abs(fine.x_m - gx) <= 0.004 and abs(fine.y_m - gy) <= 0.004
