"""Refinement below the grid: the best grid pose's cell searched exhaustively at a fine resolution.

The grid search returns the best pose on its lattice (say 1 cm, 5°); the object can sit
anywhere between lattice points. The refinement searches every pose within one grid step
(`cells`: more) of the best grid pose (x, y ± the x/y step, yaw ± the yaw step; table frame, metres and
radians) on a finer grid whose steps divide the grid's and are at most the targets (by
default 2 mm and 1°, issue 5), aligned so that it contains the grid pose itself. Its best is
the best pose at the fine resolution in that cell, by construction, and never scores below
the grid's best (which the cell contains).

A local climb (pattern search) was tried first and stopped at local maxima of the rough
score: on the real YCB-Video frames it reached the cell's best on 1 of 4 targets
(docs/performance.md), so the cell is searched whole.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import PerchError
from .search_space import SearchSpace


def fine_steps(grid_step: float, target: float) -> tuple[float, int]:
    """(step, n): the largest step grid_step / n with n a whole number that is at most target."""
    if not (math.isfinite(target) and target > 0):
        raise PerchError(f"refinement step target must be a positive number, got {target}")
    n = max(1, math.ceil(grid_step / target - 1e-9))
    return grid_step / n, n


def cell_space(
    space: SearchSpace,
    x_m: float,
    y_m: float,
    yaw_rad: float,
    target_xy_m: float,
    target_yaw_rad: float,
    cells: int = 1,
) -> SearchSpace:
    """The fine grid over the cell of grid pose (x_m, y_m, yaw_rad) of `space`: `cells` grid steps either
    side, steps at most the targets, cut to the space's x, y (and, unless the full circle, yaw) ranges."""
    if cells < 1:
        raise PerchError(f"the refinement window must reach at least 1 grid step either side, got {cells}")
    sxy, nxy = fine_steps(space.xy_step_m, target_xy_m)
    syaw, nyaw = fine_steps(space.yaw_step_rad, target_yaw_rad)
    nxy, nyaw = nxy * cells, nyaw * cells
    (x0, x1), (y0, y1) = space.x_range_m, space.y_range_m

    def cut(centre: float, lo: float, hi: float, step: float, n: int) -> tuple[float, float]:
        k = np.arange(-n, n + 1)
        v = centre + step * k
        inside = k[(v >= lo - 1e-9) & (v <= hi + 1e-9)]
        return centre + step * int(inside[0]), centre + step * int(inside[-1])

    yaw_lo, yaw_hi = yaw_rad - syaw * nyaw, yaw_rad + syaw * nyaw
    if not space.full_circle:
        yaw_lo, yaw_hi = cut(yaw_rad, *space.yaw_range_rad, syaw, nyaw)
    return SearchSpace(cut(x_m, x0, x1, sxy, nxy), cut(y_m, y0, y1, sxy, nxy), sxy, (yaw_lo, yaw_hi), syaw)
