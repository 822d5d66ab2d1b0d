"""What a search knows of each candidate's score, and the best score over yaw at each (x, y) of the table.

A search returns one score per candidate it scored. The exhaustive search scores every candidate;
the pruned one leaves out those whose silhouette bound cannot reach its top-k (their score is at
most the bound, perch_warp.bound); the coarse-to-fine one never visits most grid points (nothing
is known of them). `knowledge` turns an Outcome into two arrays over the whole space: the exact
score where known, and an upper bound everywhere, so that a maximum over any set of candidates
(a location's yaws for the heat map, the poses far from the answer for the confidence) is known
exactly when its best known score reaches every unknown candidate's bound, and is left unknown
(NaN) otherwise: values are never made up for candidates that were not scored.

Layout: the space's candidates() order, axes (x, y, yaw) with x and y first; `best_over_rest`
reduces every axis but x and y, so a further search dimension (say a resting pose) only needs
its own axis in `shape`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bound import BOUND_SLACK
from .search.base import Outcome
from .search_space import SearchSpace

# Why a candidate's score may be unknown, by search (for legends and JSON).
UNKNOWN_WHY = {
    "pruned": "pruned: not scored, since its silhouette bound is below the search's top-k",
    "coarse-to-fine": "not visited by the coarse-to-fine search",
}


@dataclass
class Knowledge:
    """Per candidate of a space (candidates() order, reshapeable to `shape`): `value` its exact score
    (-inf: it shows no feature point) or NaN where the search did not score it; `upper` an upper bound
    of its score (= value where known; bound + BOUND_SLACK where pruned; +inf where nothing is known).
    `why_unknown`: what an unknown candidate is, in words ("" when every score is known)."""

    value: np.ndarray
    upper: np.ndarray
    shape: tuple[int, ...]
    why_unknown: str

    def set_max(self, mask: np.ndarray) -> tuple[float, int, float]:
        """Over the candidates where `mask` (flat bool): the best known score, its flat index (-1 when no
        candidate is known) and the largest upper bound of the unknown ones (-inf when none is unknown).
        The best is exact when it is at least that bound."""
        v = np.where(mask, self.value, np.nan)
        unknown = np.isnan(v) & mask
        top_unknown = float(self.upper[unknown].max()) if unknown.any() else -np.inf
        known = ~np.isnan(v)
        if not known.any():
            return -np.inf, -1, top_unknown
        vk = np.where(known, v, -np.inf)
        i = int(np.argmax(vk))  # the first of equal maxima
        return float(vk[i]), i, top_unknown


def knowledge(out: Outcome, space: SearchSpace, search: str) -> Knowledge:
    """What `out` (the search `search` on `space`) knows of each candidate's score; see the module doc."""
    shape = tuple(len(a) for a in space.axes())
    n = int(np.prod(shape))
    if out.flat is not None:  # a subset scored (coarse-to-fine): the rest is unknown, unbounded
        value, upper = np.full(n, np.nan), np.full(n, np.inf)
        value[out.flat], upper[out.flat] = out.scores, out.scores
        why = UNKNOWN_WHY.get(search, f"not scored by the {search} search")
        return Knowledge(value, upper, shape, why if len(out.flat) < n else "")
    scores = np.asarray(out.scores, dtype=np.float64)
    if out.bounds is None:  # every candidate scored (-inf: no feature point)
        return Knowledge(scores.copy(), scores.copy(), shape, "")
    # Pruned: a -inf score is exact where the bound is -inf too (no feature point), else unknown.
    unknown = ~np.isfinite(scores) & np.isfinite(out.bounds)
    value = np.where(unknown, np.nan, scores)
    upper = np.where(unknown, out.bounds + BOUND_SLACK, scores)
    return Knowledge(value, upper, shape, UNKNOWN_WHY["pruned"] if unknown.any() else "")


@dataclass
class ScoreMap:
    """The best score over yaw (and any further search axis) at each (x, y) cell of the searched table
    grid (table frame; cell centres xs_m, ys_m in metres, step_m apart). `best` (nx, ny): exact where
    finite; -inf where no candidate of the cell shows a feature point; NaN where not known (a candidate
    of the cell was not scored and might score higher than those that were). `upper` (nx, ny): an upper
    bound of the cell's best (= best where known; +inf where nothing bounds it). `best_yaw_rad` (nx, ny):
    the yaw of the cell's best (NaN where best is not finite). `why_unknown`: what NaN cells are.
    `seen` (nx, ny): the best score among the cell's scored candidates, a lower bound of `best` known
    even where `best` is not (a coarse-to-fine search's visits; -inf where none was scored), and
    `seen_yaw_rad` its yaw (NaN there); None in maps written before they existed."""

    xs_m: np.ndarray
    ys_m: np.ndarray
    step_m: float
    best: np.ndarray
    upper: np.ndarray
    best_yaw_rad: np.ndarray
    why_unknown: str
    seen: np.ndarray | None = None
    seen_yaw_rad: np.ndarray | None = None

    @property
    def n_unknown(self) -> int:
        return int(np.isnan(self.best).sum())

    def save(self, f) -> None:
        """Write as a compressed .npz into the binary file f (float32 scores: a picture's precision)."""
        seen = (
            {}
            if self.seen is None
            else {"seen": self.seen.astype(np.float32), "seen_yaw_rad": self.seen_yaw_rad.astype(np.float32)}
        )
        np.savez_compressed(
            f, xs_m=self.xs_m, ys_m=self.ys_m, step_m=self.step_m, best=self.best.astype(np.float32),
            upper=self.upper.astype(np.float32), best_yaw_rad=self.best_yaw_rad.astype(np.float32),
            why_unknown=np.array(self.why_unknown), **seen,
        )  # fmt: skip

    @classmethod
    def load(cls, path) -> ScoreMap:
        with np.load(path) as z:
            grids = (z[k].astype(np.float64) for k in ("best", "upper", "best_yaw_rad"))
            seen = [z[k].astype(np.float64) if k in z.files else None for k in ("seen", "seen_yaw_rad")]
            return cls(z["xs_m"], z["ys_m"], float(z["step_m"]), *grids, str(z["why_unknown"]), *seen)

    def peaks(self, n: int, sep_steps: int) -> list[tuple[float, float, float, float]]:
        """Up to n distinct peaks (x_m, y_m, yaw_rad, score), best first: known cells more than
        sep_steps cells apart in x or in y (perch_warp.peaks.distinct_peaks)."""
        from .peaks import distinct_peaks

        i, j = np.nonzero(np.isfinite(self.best))
        order = np.lexsort((j, i, -self.best[i, j]))
        cells = [(float(self.xs_m[a]), float(self.ys_m[b]), float(self.best_yaw_rad[a, b]), float(self.best[a, b]))
                 for a, b in zip(i[order], j[order], strict=True)]  # fmt: skip
        return [cells[k] for k in distinct_peaks(cells, n, sep_steps * self.step_m)]


def best_over_rest(
    k: Knowledge, xy_axes: tuple[int, int] = (0, 1)
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(best, upper, argbest, seen) per (x, y) cell: the maximum over every other axis of k's candidates,
    as in ScoreMap (argbest: the flat index over the other axes of the best known candidate, -1 where
    none; seen: that candidate's score, -inf where none)."""

    def per_cell(a: np.ndarray) -> np.ndarray:
        a = np.moveaxis(a.reshape(k.shape), xy_axes, (0, 1))
        return a.reshape(a.shape[0], a.shape[1], -1)

    v, u = per_cell(k.value), per_cell(k.upper)
    unknown = np.isnan(v)
    known_v = np.where(unknown, -np.inf, v)
    arg = np.argmax(known_v, axis=2)
    known_max = np.take_along_axis(known_v, arg[..., None], axis=2)[..., 0]
    top_unknown = np.where(unknown, u, -np.inf).max(axis=2)
    exact = known_max >= top_unknown
    best = np.where(exact, known_max, np.nan)
    arg = np.where((~unknown).any(axis=2), arg, -1)
    return best, np.maximum(known_max, top_unknown), arg, known_max


def score_map(k: Knowledge, space: SearchSpace) -> ScoreMap:
    """The ScoreMap of a (x, y, yaw) space from what its search knows."""
    xs, ys, yaws = space.axes()
    best, upper, arg, seen = best_over_rest(k)
    seen_yaw = np.where(arg >= 0, yaws[np.clip(arg, 0, None)], np.nan)
    yaw = np.where(np.isfinite(best), seen_yaw, np.nan)  # the best, where known, is the best seen
    why = k.why_unknown if np.isnan(best).any() else ""
    return ScoreMap(xs, ys, space.xy_step_m, best, upper, yaw, why, seen, seen_yaw)


def stacked(ks: list[Knowledge]) -> Knowledge:
    """Several searches of one (x, y, yaw) space (one per resting pose) as one Knowledge over
    (x, y, pose, yaw): best_over_rest then takes the best over resting pose and yaw per cell."""
    nx, ny, n_yaw = ks[0].shape

    def stack(arrays: list[np.ndarray]) -> np.ndarray:
        return np.stack([a.reshape(nx, ny, n_yaw) for a in arrays], axis=2).reshape(-1)

    why = next((k.why_unknown for k in ks if k.why_unknown), "")
    return Knowledge(stack([k.value for k in ks]), stack([k.upper for k in ks]), (nx, ny, len(ks), n_yaw), why)


def score_map_over_rests(ks: list[Knowledge], space: SearchSpace) -> tuple[ScoreMap, np.ndarray]:
    """The ScoreMap of one space searched under several resting poses (ks: each pose's Knowledge): the
    best over resting pose and yaw per cell; and, per cell, the index of the pose of that best (-1 where
    the cell's best is not finite)."""
    xs, ys, yaws = space.axes()
    best, upper, arg, seen = best_over_rest(stacked(ks))
    finite = np.isfinite(best)
    pose, k_yaw = np.divmod(np.clip(arg, 0, None), len(yaws))
    seen_yaw = np.where(arg >= 0, yaws[k_yaw], np.nan)
    yaw = np.where(finite, seen_yaw, np.nan)
    why = next((k.why_unknown for k in ks if k.why_unknown), "") if np.isnan(best).any() else ""
    smap = ScoreMap(xs, ys, space.xy_step_m, best, upper, yaw, why, seen, seen_yaw)
    return smap, np.where(finite, pose, -1)
