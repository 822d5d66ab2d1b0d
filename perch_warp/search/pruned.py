"""The pruned search: the exhaustive search's top-k, scoring only the candidates that could be in it.

Every candidate is bounded by its silhouette (perch_warp.bound), then scored best bound first until
no remaining bound reaches the k-th best score. best_first is shared with the pyramid search.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bound import next_to_score
from ..peaks import kth_location_score
from ..search_space import SearchSpace
from . import scoring
from .base import Outcome, kth_largest
from .scoring import PoseSource, ScoringService, SearchStats


@dataclass
class BestFirst:
    """What best_first did: the indices scored, rounds of batches, every candidate's bound (-inf where
    not bounded) and how many were bounded."""

    scored: np.ndarray
    rounds: int
    bounds: np.ndarray
    bounded: int


@dataclass
class Incumbent:
    """The best scores of earlier searches of the same space under other resting poses
    (search/rests.py), which a later search must beat: its threshold starts there and stays exact,
    since the answer is the top-k of all poses together. `top`: the k best candidate scores so far;
    `location_best`: each location's (x, y) best over yaw and poses, -inf where none (when the search
    keeps locations: several refined peaks)."""

    top: np.ndarray
    location_best: np.ndarray

    @classmethod
    def empty(cls, space: SearchSpace) -> Incumbent:
        xs, ys, _ = space.axes()
        return cls(np.empty(0), np.full(len(xs) * len(ys), -np.inf))

    def add(self, out: Outcome, space: SearchSpace, k: int) -> None:
        """Fold in a search's outcome over `space` (its scores in the space's order or at out.flat)."""
        flat = np.arange(len(out.scores)) if out.flat is None else out.flat
        ok = np.isfinite(out.scores)
        self.top = np.sort(np.concatenate([self.top, out.scores[ok]]))[::-1][:k]
        np.maximum.at(self.location_best, flat[ok] // len(space.axes()[2]), out.scores[ok])


def run(service: ScoringService, space: SearchSpace, prior: Incumbent | None = None) -> Outcome:
    """Scores (-inf where not scored) in the space's order and what the search did; with `prior`,
    candidates that cannot beat the earlier resting poses' k-th best are not scored either."""
    stats = SearchStats()
    scores = np.full(len(space), -np.inf)
    k = service.config.pool
    n_yaw = len(space.axes()[2])
    by_location = service.config.refine and service.config.refine_peaks > 1

    def kth_best(scored: np.ndarray) -> float:
        if by_location:  # the k-th best location (best over yaw): perch_warp.peaks
            loc_prior = None if prior is None else prior.location_best
            return kth_location_score(scored, scores[scored], n_yaw, k, loc_prior)
        if prior is None:
            return kth_largest(scores[scored], k)
        return kth_largest(np.concatenate([prior.top, scores[scored]]), k)

    bf = best_first(service, PoseSource.of_space(space), scores, kth_best, stats)
    extra = {
        "bounded": bf.bounded,
        "scored": len(bf.scored),
        "rounds": bf.rounds,
        "bound_rays": stats.bound_rays,
        "k": k,  # the rank whose score a bound had to reach
    }
    return Outcome(scores, len(bf.scored), stats, extra=extra, bounds=bf.bounds)


def _bound_all(service: ScoringService, poses: PoseSource, stats: SearchStats):
    """Every candidate's bound (-inf without feature points), its box size in pixels, and how many show points."""
    bounds = np.full(poses.n, -np.inf)
    box_px = np.zeros(poses.n, dtype=np.int64)
    n_live = 0
    for idx in poses.chunks():
        c = service.setup(poses, idx)
        box_px[idx] = c.boxes[:, 2].astype(np.int64) * c.boxes[:, 3]
        part = np.full(len(idx), -np.inf)
        service.bound_some(c, c.live, part, stats)
        bounds[idx] = part
        n_live += len(c.live)
    return bounds, box_px, n_live


def best_first(service: ScoringService, poses: PoseSource, scores: np.ndarray, kth_best, stats: SearchStats):
    """Bound the candidates of poses (those showing feature points), then score them best bound
    first, a round of batches at a time, until no remaining bound reaches kth_best(indices scored
    so far). scores[i] stays -inf for the others: those without feature points (whose score is -inf)
    and those ruled out (whose score is below the final threshold). Poses and boxes are set up a chunk
    at a time, for the bounds and again for each round; only a bound and a box size per candidate are
    kept. The progress bar counts a candidate as done once it is scored or can no longer be (its bound
    below the threshold so far, or no feature points), so that its rate and time left follow where the
    search will really end. Returns a BestFirst."""
    bounds, box_px, n_live = _bound_all(service, poses, stats)
    # A candidate without feature points scores -inf whatever it shows: never worth scoring.
    order = np.argsort(-bounds, kind="stable")
    order = order[np.isfinite(bounds[order])]
    ranked = bounds[order]
    report = _reporter(service.bar, n_live)
    # A round: about one budget of rays per thread, so that the first rounds set the threshold
    # early and each later one stops as soon as the bounds fall below it.
    per_round = service.budget() * service.threads()
    threshold = kth_best(order[:0])
    pos = 0
    rounds = 0
    while pos < len(order):
        end = min(next_to_score(ranked, pos, threshold), pos + scoring.SETUP_CHUNK)
        if end <= pos:
            break
        sizes = box_px[order[pos:end]]
        end = pos + max(1, int(np.searchsorted(np.cumsum(sizes), per_round, side="right")))
        idx = order[pos:end]
        c = service.setup(poses, idx)
        part = np.full(len(idx), -np.inf)
        service.score_some(c, np.arange(len(idx)), part, stats, progress=False)
        scores[idx] = part
        pos = end
        rounds += 1
        threshold = kth_best(order[:pos])
        report(n_live - (next_to_score(ranked, pos, threshold) - pos))
    report(n_live)
    return BestFirst(order[:pos], rounds, bounds, n_live)


def _reporter(bar, n_live: int):
    """report(done): the bar's count raised to `done` (never lowered); the bar grows by n_live first."""
    if bar is not None:
        bar.total += n_live
        bar.refresh()
    reported = 0

    def report(done: int) -> None:
        nonlocal reported
        if bar is not None and done > reported:
            bar.update(done - reported)
            reported = done

    return report
