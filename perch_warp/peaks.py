"""Distinct peaks of a grid search (re-ranking before the refinement, issue 17 (g)).

Small textured objects have score peaks narrower than a grid step: on a 1 cm / 5° grid the
true pose's grid neighbours can score below a distractor's grid pose, although refined below
the grid the truth scores higher. Refining only the grid's single best therefore loses such
targets. With several peaks, the search ranks *locations* (x, y on the table) by their best
score over yaw and keeps the best `pool` of them (exactly, also when pruned); `distinct_peaks`
picks, best first, locations farther apart than a few grid steps (greedy non-maximum
suppression in x, y: the yaw variants of one place are one peak), and each peak's cell is
refined: the best refined pose wins.

A first version suppressed in (x, y, yaw) and kept the best candidates rather than locations:
all its peaks were yaw variants of the same distractor (docs/accuracy.md).
"""

from __future__ import annotations

import numpy as np

# Two peaks are one when their locations lie within this many grid steps in x and in y.
SEPARATION_STEPS = 3


def peak_pool(top_k: int, peaks: int) -> int:
    """How many best candidates (one peak) or best locations (several peaks) a search keeps."""
    return top_k if peaks <= 1 else max(top_k, 32 * peaks)


def location_best(flat: np.ndarray, scores: np.ndarray, n_yaw: int) -> np.ndarray:
    """The flat index of the best candidate of each location (flat // n_yaw, flat indices in the space's
    candidates() order) that has a finite score; ties go to the lower flat index."""
    flat = np.asarray(flat, dtype=np.int64)
    ok = np.isfinite(scores)
    flat, scores = flat[ok], scores[ok]
    order = np.lexsort((flat, -scores))  # best first, ties to the lower index
    loc = flat[order] // n_yaw
    _, first = np.unique(loc, return_index=True)
    return flat[order][first]


def top_location_candidates(flat: np.ndarray, scores: np.ndarray, n_yaw: int, m: int) -> np.ndarray:
    """Positions in (flat, scores) of the best candidate of each of the m best locations, best first
    (ties to the lower flat index); flat ascending, as every search returns it."""
    flat = np.asarray(flat, dtype=np.int64)
    best = location_best(flat, scores, n_yaw)
    pos = np.searchsorted(flat, best)
    return pos[np.lexsort((best, -scores[pos]))[:m]]


def kth_location_score(
    flat: np.ndarray, scores: np.ndarray, n_yaw: int, k: int, prior: np.ndarray | None = None
) -> float:
    """The k-th best location's best score among these candidates; -inf with fewer than k locations.
    `prior` (one value per location of the space, -inf where none): each location's best score from
    other searches of the same space (other resting poses), merged in."""
    ok = np.isfinite(scores)
    if prior is None and not ok.any():
        return -np.inf
    loc = np.asarray(flat, dtype=np.int64)[ok] // n_yaw
    best = np.full(int(loc.max()) + 1, -np.inf) if prior is None else prior.copy()
    np.maximum.at(best, loc, scores[ok])
    best = best[np.isfinite(best)]
    n = len(best)
    return float(np.partition(best, n - k)[n - k]) if 0 < k <= n else -np.inf


def distinct_peaks(candidates: list[tuple[float, float, float, float]], n: int, xy_sep_m: float) -> list[int]:
    """Indices of up to n candidates (x_m, y_m, yaw_rad, score; table frame, sorted best first), best
    first, each farther than xy_sep_m in x or in y from every candidate kept before it, whatever its
    yaw: greedy non-maximum suppression of locations in the grid's box metric."""
    kept: list[int] = []
    tol = 1e-9
    for i, (x, y, _, _) in enumerate(candidates):
        if len(kept) == n:
            break
        if all(abs(candidates[j][0] - x) > xy_sep_m + tol or abs(candidates[j][1] - y) > xy_sep_m + tol for j in kept):
            kept.append(i)
    return kept


# Two yaws of one place are one peak when they lie within this many yaw steps: the refinement
# searches one yaw step either side of a grid yaw, so peaks further apart have disjoint cells.
YAW_SEPARATION_STEPS = 2


def yaw_peaks(scores: np.ndarray, m: int, circular: bool, first: int | None = None) -> list[int]:
    """Indices of up to m yaw peaks of one place: scores (n_yaw,) over the grid's yaws in order (-inf
    where not shown). A peak is a local maximum over yaw (neighbours wrap around on the full circle);
    peaks are kept best first (ties to the lower index), each more than YAW_SEPARATION_STEPS from those
    kept before. `first`: an index kept first whatever its rank (the place's grid best, already known)."""
    s = np.asarray(scores, dtype=np.float64)
    n = len(s)
    if circular:
        left, right = np.roll(s, 1), np.roll(s, -1)
    else:
        left = np.concatenate([[-np.inf], s[:-1]])
        right = np.concatenate([s[1:], [-np.inf]])
    local = np.isfinite(s) & (s >= left) & (s >= right)
    order = [int(i) for i in np.lexsort((np.arange(n), -s)) if local[i]]
    kept: list[int] = [] if first is None else [int(first)]

    def apart(i: int, j: int) -> bool:
        d = abs(i - j)
        return (min(d, n - d) if circular else d) > YAW_SEPARATION_STEPS

    for i in order:
        if len(kept) >= m:
            break
        if all(apart(i, j) for j in kept):
            kept.append(i)
    return kept[:m]
