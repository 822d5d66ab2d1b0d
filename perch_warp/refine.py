"""Refinement below the grid: a pattern search from the best grid pose down to a fine resolution.

The grid search returns the best pose on its lattice (say 1 cm, 5°); the object can sit
anywhere between lattice points. From the best grid pose, score the 26 neighbours at
half the grid's steps (x, y in metres and yaw in radians, table frame); move to the best
neighbour while one scores higher, otherwise halve the steps that are still above their
targets; stop when no neighbour at the target resolution scores higher. The pose found is
a local maximum of the score on a lattice no coarser than the targets (by default 2 mm and
1°, issue 5). It only climbs: the refined score is never below the grid's.

Plain functions around a scoring callback, so the walk is testable on any function.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .errors import PerchError

#: (x_m, y_m, yaw_rad) arrays -> scores (higher is better; -inf: nothing to compare)
ScoreFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]

# Moves at one step size before halving anyway (or, at the finest steps, stopping): only strictly
# higher scores move, so the walk cannot cycle; this only bounds the cost of a long climb.
MAX_MOVES_PER_STEP = 8


@dataclass
class Refinement:
    """Where the walk ended and what it cost."""

    x_m: float
    y_m: float
    yaw_rad: float
    score: float
    step_xy_m: float  # the final lattice's steps: the pose is a local maximum at this resolution
    step_yaw_rad: float
    evaluated: int  # poses scored (each at most once)
    converged: bool  # False: still climbing when MAX_MOVES_PER_STEP moves at the finest steps ran out
    path: list[tuple[float, float, float, float]] = field(default_factory=list)  # (x, y, yaw, score) per move

    def to_dict(self) -> dict:
        return {
            "step_xy_m": self.step_xy_m,
            "step_yaw_deg": math.degrees(self.step_yaw_rad),
            "evaluated": self.evaluated,
            "moves": len(self.path) - 1,
            "converged": self.converged,
            "from": {"x_m": self.path[0][0], "y_m": self.path[0][1], "yaw_deg": math.degrees(self.path[0][2])},
            "score_gain": self.score - self.path[0][3],
        }


def neighbours(
    x_m: float, y_m: float, yaw_rad: float, step_xy_m: float, step_yaw_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 26 poses one step away in x, y and/or yaw (table frame), in a fixed order."""
    d = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)])
    return x_m + d[:, 0] * step_xy_m, y_m + d[:, 1] * step_xy_m, yaw_rad + d[:, 2] * step_yaw_rad


def refine_pose(
    score_fn: ScoreFn,
    start: tuple[float, float, float, float],
    step_xy_m: float,
    step_yaw_rad: float,
    target_xy_m: float = 0.002,
    target_yaw_rad: float = math.radians(1.0),
    x_range_m: tuple[float, float] = (-math.inf, math.inf),
    y_range_m: tuple[float, float] = (-math.inf, math.inf),
    yaw_range_rad: tuple[float, float] | None = None,
) -> Refinement:
    """Climb from start = (x_m, y_m, yaw_rad, score), first steps step_xy_m / step_yaw_rad (half
    the grid's), until no neighbour at steps <= the targets scores higher. x, y and yaw stay
    within their ranges (the searched region); yaw_range_rad None: the full circle, wrapped to [0, 2π)."""
    for name, v in (
        ("refinement x/y step", step_xy_m),
        ("refinement yaw step", step_yaw_rad),
        ("refinement x/y target", target_xy_m),
        ("refinement yaw target", target_yaw_rad),
    ):
        if not (math.isfinite(v) and v > 0):
            raise PerchError(f"{name} must be a positive number, got {v}")
    x, y, yaw, best = (float(v) for v in start)
    seen: dict[tuple[int, int, int], float] = {}
    path = [(x, y, yaw, best)]
    sxy, syaw = step_xy_m, step_yaw_rad
    moves = 0
    evaluated = 0
    converged = True

    def key(a: float, b: float, c: float) -> tuple[int, int, int]:
        # Poses compared at 1 µm / 1 µrad: the same pose reached along two routes is scored once.
        return round(a * 1e6), round(b * 1e6), round(c * 1e6)

    seen[key(x, y, yaw)] = best
    while True:
        nx, ny, nyaw = neighbours(x, y, yaw, sxy, syaw)
        nx = np.clip(nx, *x_range_m)
        ny = np.clip(ny, *y_range_m)
        nyaw = np.mod(nyaw, 2 * math.pi) if yaw_range_rad is None else np.clip(nyaw, *yaw_range_rad)
        keys = [key(a, b, c) for a, b, c in zip(nx.tolist(), ny.tolist(), nyaw.tolist(), strict=True)]
        new = [i for i, k in enumerate(keys) if k not in seen and k not in keys[:i]]
        if new:
            sc = np.asarray(score_fn(nx[new], ny[new], nyaw[new]), dtype=np.float64)
            evaluated += len(new)
            for i, s in zip(new, sc.tolist(), strict=True):
                seen[keys[i]] = s
        scores = np.array([seen[k] for k in keys])
        i = int(np.argmax(scores))  # the first of equal maxima: deterministic
        final = sxy <= target_xy_m and syaw <= target_yaw_rad
        if scores[i] > best:
            x, y, yaw, best = float(nx[i]), float(ny[i]), float(nyaw[i]), float(scores[i])
            path.append((x, y, yaw, best))
            moves += 1
            if moves < MAX_MOVES_PER_STEP:
                continue
            if final:
                converged = False  # still climbing at the finest steps: stopped by the cap
                break
        elif final:
            break
        sxy = sxy / 2 if sxy > target_xy_m else sxy
        syaw = syaw / 2 if syaw > target_yaw_rad else syaw
        moves = 0
    return Refinement(x, y, yaw, best, sxy, syaw, evaluated, converged, path)
