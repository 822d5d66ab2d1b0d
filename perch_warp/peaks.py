"""Distinct peaks of a grid search's best candidates (re-ranking before the refinement, issue 17 (g)).

Small textured objects have score peaks narrower than a grid step: on a 1 cm / 5° grid the
true pose's grid neighbours can score below a distractor's, although refined below the grid
the truth scores higher. Refining only the grid's single best therefore loses such targets.
The search keeps its best `pool` grid candidates; `distinct_peaks` picks, best first, those
whose refinement cells cannot overlap (greedy non-maximum suppression on the grid), and each
peak's cell is refined: the best refined pose wins.
"""

from __future__ import annotations

import math

import numpy as np


def distinct_peaks(
    candidates: list[tuple[float, float, float, float]], n: int, xy_sep_m: float, yaw_sep_rad: float
) -> list[int]:
    """Indices of up to n candidates (x_m, y_m, yaw_rad, score; table frame, sorted best first), best
    first, each farther than xy_sep_m in x or y, or yaw_sep_rad in yaw (on the circle), from every
    candidate kept before it: greedy non-maximum suppression in the grid's box metric."""
    kept: list[int] = []
    for i, (x, y, yaw, _) in enumerate(candidates):
        if len(kept) == n:
            break
        if all(not _near(candidates[j], x, y, yaw, xy_sep_m, yaw_sep_rad) for j in kept):
            kept.append(i)
    return kept


def _near(c, x: float, y: float, yaw: float, xy_sep_m: float, yaw_sep_rad: float) -> bool:
    dyaw = abs((c[2] - yaw + math.pi) % (2 * math.pi) - math.pi)
    tol = 1e-9
    return abs(c[0] - x) <= xy_sep_m + tol and abs(c[1] - y) <= xy_sep_m + tol and dyaw <= yaw_sep_rad + tol


def peak_pool(top_k: int, peaks: int) -> int:
    """Best grid candidates a search keeps to find `peaks` distinct peaks among (the top_k reported
    included): a peak's own grid neighbours fill the first few dozen places."""
    return top_k if peaks <= 1 else max(top_k, 32 * peaks)


def as_array(candidates) -> np.ndarray:
    return np.asarray(candidates, dtype=np.float64).reshape(-1, 4)
