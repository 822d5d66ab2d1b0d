"""Refinement below the grid: the walk on analytic scores, then the engine on a photographed scene."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.refine import refine_pose
from perch_warp.search_space import SearchSpace


def _ang(a, b):
    return np.abs((np.asarray(a) - b + math.pi) % (2 * math.pi) - math.pi)


class Bowl:
    """A smooth single-peaked score with its maximum at (x0, y0, yaw0); counts every pose scored."""

    def __init__(self, x0, y0, yaw0):
        self.peak = (x0, y0, yaw0)
        self.calls: list[tuple[float, float, float]] = []

    def __call__(self, x, y, yaw):
        self.calls += list(zip(x.tolist(), y.tolist(), yaw.tolist(), strict=True))
        x0, y0, yaw0 = self.peak
        return 1.0 - ((x - x0) / 0.01) ** 2 - ((y - y0) / 0.02) ** 2 - (_ang(yaw, yaw0) / 0.1) ** 2

    def at(self, x, y, yaw):
        return float(self(np.array([x]), np.array([y]), np.array([yaw]))[0])


def test_climbs_from_a_grid_pose_to_the_peak_within_the_targets():
    f = Bowl(0.0137, -0.0222, math.radians(33.3))
    start = (0.01, -0.02, math.radians(30.0))
    r = refine_pose(f, (*start, f.at(*start)), 0.005, math.radians(2.5))
    assert abs(r.x_m - 0.0137) <= 0.002 and abs(r.y_m + 0.0222) <= 0.002
    assert math.degrees(_ang(r.yaw_rad, math.radians(33.3))) <= 1.0
    assert r.step_xy_m <= 0.002 and r.step_yaw_rad <= math.radians(1.0) + 1e-12 and r.converged
    # Each pose scored once (the start's score was given), and the count says so.
    called = [(round(a, 9), round(b, 9), round(c, 9)) for a, b, c in f.calls[1:]]
    assert len(called) == len(set(called)) == r.evaluated
    assert r.score > r.path[0][3] and r.score == pytest.approx(f.at(r.x_m, r.y_m, r.yaw_rad))
    # A local maximum at the final steps: no neighbour scores higher.
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dk in (-1, 0, 1):
                assert f.at(r.x_m + dx * r.step_xy_m, r.y_m + dy * r.step_xy_m, r.yaw_rad + dk * r.step_yaw_rad) <= (
                    r.score
                )


def test_stays_at_a_peak_it_starts_on_and_never_goes_down():
    f = Bowl(0.0, 0.0, 1.0)
    r = refine_pose(f, (0.0, 0.0, 1.0, f.at(0.0, 0.0, 1.0)), 0.005, math.radians(2.5))
    assert (r.x_m, r.y_m, r.yaw_rad) == (0.0, 0.0, 1.0) and len(r.path) == 1
    assert r.evaluated == 26 * 3  # the neighbourhood at 5, 2.5 and 1.25 mm (yaw 2.5°, 1.25°, 0.625°)


def test_keeps_to_the_region_and_wraps_yaw():
    f = Bowl(0.05, 0.0, math.radians(359.0))
    start = (0.02, 0.0, math.radians(1.0))
    r = refine_pose(f, (*start, f.at(*start)), 0.005, math.radians(2.5), x_range_m=(0.0, 0.03))
    assert r.x_m == pytest.approx(0.03)  # the peak lies beyond the region's edge
    assert math.degrees(_ang(r.yaw_rad, math.radians(359.0))) <= 1.0  # across 0°
    assert 0.0 <= r.yaw_rad < 2 * math.pi
    # A yaw range that is not the full circle is clipped, not wrapped.
    r2 = refine_pose(f, (*start, f.at(*start)), 0.005, math.radians(2.5), yaw_range_rad=(0.0, math.radians(90)))
    assert r2.yaw_rad == pytest.approx(0.0)


def test_refuses_non_positive_steps():
    with pytest.raises(PerchError, match="refinement x/y target"):
        refine_pose(Bowl(0, 0, 0), (0, 0, 0, 1.0), 0.005, 0.01, target_xy_m=0.0)


@pytest.fixture(scope="module")
def scene():
    return demo_scene(seed=1)


def test_engine_refines_the_photographed_box_below_its_grid(scene, caffe_weights):
    """The demo's box (lit, shadowed, noisy photo) at an off-grid pose: a 1 cm / 30° grid finds it
    within a step; refinement brings it within 2 mm and 1° and scores higher."""
    gx, gy, gyaw = scene.truth_xy_yaw
    cx, cy = round(gx / 0.01) * 0.01 + 0.01, round(gy / 0.01) * 0.01 - 0.01
    space = SearchSpace((cx - 0.03, cx + 0.03), (cy - 0.03, cy + 0.03), 0.01, (0, 2 * math.pi), math.radians(30))
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    grid = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(refine=False)).estimate(*args)
    fine = Engine(scene.mesh, caffe_weights, DEVICE).estimate(*args)
    grid_yaw_err = math.degrees(_ang(grid.yaw_rad, gyaw))
    assert grid_yaw_err > 1.0  # so the test shows the refinement at work
    assert abs(fine.x_m - gx) <= 0.002 and abs(fine.y_m - gy) <= 0.002
    assert math.degrees(_ang(fine.yaw_rad, gyaw)) <= 1.0
    ref = fine.info["refine"]
    assert fine.score > grid.score and ref["score_gain"] == pytest.approx(fine.score - grid.score)
    assert (ref["from"]["x_m"], ref["from"]["y_m"]) == (grid.x_m, grid.y_m)
    # The grid search itself is unchanged, and its counters do not include the refinement's.
    assert (fine.n_scored, fine.info["rays"]) == (grid.n_scored, grid.info["rays"])
    assert ref["rays"] > 0 and "refine" in fine.timings_s
    # The runners-up stay grid poses, below the refined best.
    assert all(c.score <= fine.score for c in fine.top_k[1:])
