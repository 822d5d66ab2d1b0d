import math

import numpy as np
import pytest

from perch_warp.camera import Camera
from perch_warp.errors import PerchError
from perch_warp.scene import look_at_table
from perch_warp.search_space import SearchSpace


def test_grid_is_inclusive_in_xy_and_open_on_the_full_circle():
    s = SearchSpace((-0.1, 0.1), (0.0, 0.05), 0.01, (0, 2 * math.pi), math.radians(5))
    xs, ys, yaws = s.axes()
    assert len(xs) == 21 and len(ys) == 6 and len(yaws) == 72
    assert len(s) == 21 * 6 * 72
    x, y, yaw = s.candidates()
    assert len(x) == len(s) and yaw[1] - yaw[0] == pytest.approx(math.radians(5))
    assert xs[-1] == pytest.approx(0.1)


def test_candidates_by_flat_index_are_those_of_the_whole_grid():
    s = SearchSpace((-0.05, 0.03), (0.1, 0.16), 0.02, (0.0, 2 * math.pi), math.radians(45))
    x, y, yaw = s.candidates()
    assert len(x) == len(s) == 5 * 4 * 8
    ax, ay, ayaw = s.at(np.arange(len(s)))
    np.testing.assert_array_equal(ax, x)
    np.testing.assert_array_equal(ay, y)
    np.testing.assert_array_equal(ayaw, yaw)
    pick = np.array([159, 0, 37, 8])
    for a, b in zip(s.at(pick), (x[pick], y[pick], yaw[pick]), strict=True):
        np.testing.assert_array_equal(a, b)


def test_samples_are_distinct_grid_candidates_and_repeat_with_the_seed():
    s = SearchSpace((-0.05, 0.03), (0.1, 0.16), 0.02, (0.0, 2 * math.pi), math.radians(45))
    grid = set(zip(*(a.round(9).tolist() for a in s.candidates()), strict=True))
    x, y, yaw = s.sample(50, seed=3)
    picked = list(zip(x.round(9).tolist(), y.round(9).tolist(), yaw.round(9).tolist(), strict=True))
    assert len(set(picked)) == 50 and set(picked) <= grid
    np.testing.assert_array_equal(s.sample(50, seed=3)[2], yaw)
    assert len(s.sample(1000, seed=0)[0]) == len(s)  # at most the whole grid


def test_partial_yaw_range_includes_its_end():
    s = SearchSpace((0, 0), (0, 0), 0.01, (0, math.radians(90)), math.radians(30))
    assert len(s) == 4


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(x_range_m=(0.1, -0.1)), "empty"),
        (dict(xy_step_m=0.0), "positive"),
        (dict(yaw_step_rad=float("nan")), "finite"),
    ],
)
def test_bad_grids_are_refused(kw, match):
    args = dict(x_range_m=(0, 0.1), y_range_m=(0, 0.1), xy_step_m=0.01, yaw_step_rad=0.1)
    args.update(kw)
    with pytest.raises(PerchError, match=match):
        len(SearchSpace(**args))


def test_visible_table_is_centred_on_the_view_and_clipped():
    table = look_at_table(0.8, 30.0, 0.0)
    cam = Camera(np.array([[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1.0]]), 640, 480)
    s = SearchSpace.visible_table(cam, table, 0.01, math.radians(10), clip_m=0.5)
    (x0, x1), (y0, y1) = s.x_range_m, s.y_range_m
    assert x1 - x0 <= 0.5 + 0.02 and y1 - y0 <= 0.5 + 0.02
    assert x0 < 0 < x1 and y0 < 0 < y1  # the camera looks at the table origin
