"""The search over (resting pose, x, y, yaw): the configured search once per resting pose, on one photo.

Every resting pose gets the same scoring service (the photo's features and rarity computed once; only
the service's resting pose differs), so the cost is the sum of the per-pose searches: linear in the
number of poses. The pruned search stays exact across poses: each pose's search starts from the k-th
best score of the poses searched before it (`pruned.Incumbent`), and a candidate is left unscored only
when its own silhouette bound is below that, so no candidate of the joint top-k is missed. Poses are
searched in the order given (most probable first, resting.stable_rests), so the likely ones set the bar.

The joint ranking lays candidates out as (location, pose, yaw), so that with one pose it is the
single-pose ranking itself: ties go to the earlier location, then the earlier pose; with several refined
peaks a location's best is over yaw *and* pose (one place, one peak).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..peaks import top_location_candidates
from ..search_space import SearchSpace
from . import get
from .base import Outcome, top_indices
from .pruned import Incumbent
from .refine import peak_summary, refine_each, refine_place, same_pose
from .scoring import ScoringService, SearchStats

#: a scored pose: (x_m, y_m, yaw_rad, score, index of its resting pose)
Top = tuple[float, float, float, float, int]


def search_all(services: list[ScoringService], space: SearchSpace, search: str, labels: list[str]):
    """Each service's (resting pose's) search outcome, in order; the progress bar names the pose."""
    outs: list[Outcome] = []
    prior = Incumbent.empty(space) if search == "pruned" else None
    for p, service in enumerate(services):
        if service.bar is not None:
            service.bar.set_description(f"rest {p + 1}/{len(services)}: {labels[p][:40]}")
        if prior is not None:
            out = get("pruned")(service, space, prior)
            prior.add(out, space, service.config.pool)
        else:
            out = get(search)(service, space)
        outs.append(out)
    return outs


def joint_top(outs: list[Outcome], space: SearchSpace, config) -> list[Top]:
    """The best candidates over every pose (the single-pose search's ranking, on the joint layout)."""
    n_xy_yaw = len(space)
    n_yaw = len(space.axes()[2])
    n_rest = len(outs)
    flats, scores = [], []
    for p, out in enumerate(outs):
        flat = np.arange(n_xy_yaw) if out.flat is None else out.flat
        loc, k = np.divmod(flat, n_yaw)
        flats.append((loc * n_rest + p) * n_yaw + k)  # (location, pose, yaw)
        scores.append(out.scores)
    flat, sc = np.concatenate(flats), np.concatenate(scores)
    order = np.argsort(flat, kind="stable")
    flat, sc = flat[order], sc[order]
    if not np.isfinite(sc).any():
        return []
    if config.refine and config.refine_peaks > 1:
        pick = top_location_candidates(flat, sc, n_rest * n_yaw, config.pool)
    else:
        pick = top_indices(sc, config.top_k)
    loc, rest = np.divmod(flat[pick], n_rest * n_yaw)
    p, k = np.divmod(rest, n_yaw)
    x, y, yaw = space.at(loc * n_yaw + k)
    return [(float(x[i]), float(y[i]), float(yaw[i]), float(sc[j]), int(p[i])) for i, j in enumerate(pick)]


def refine_joint(services: list[ScoringService], space: SearchSpace, top: list[Top], search: str, config):
    """search.refine's refinement on the joint top: the best peak (or the best `refine_peaks` distinct
    places, each at its own best pose) refined under its resting pose; the best refined first, then the
    runners-up. Returns (top, info)."""
    n = max(config.refine_peaks, 1)

    def refine_at(i: int):
        p = top[i][4]
        best, info = refine_place(services[p], space, top[i][:4], search)  # --refine-yaws yaws of the place
        return (*best, p), info

    idx, refined, order = refine_each(top, n, space, refine_at)
    info = dict(refined[order[0]][1])
    if n > 1:
        info["peaks"] = [{**peak_summary(c, i), "rest": c[4]} for c, i in refined]
    best = [refined[m][0] for m in order]
    drop = [top[i] for i in idx] + best  # the refined grid poses, and runners-up a refinement landed on

    def same(a: Top, b: Top) -> bool:
        return a[4] == b[4] and same_pose(a, b)

    return [*best, *(c for c in top if not any(same(c, d) for d in drop))], info


def combined_extra(outs: list[Outcome], search: str) -> tuple[int, SearchStats, dict]:
    """Candidates scored, the summed cost, and the per-search facts summed over poses (for the result)."""
    stats = SearchStats()
    for o in outs:
        stats.batches += o.stats.batches
        stats.rays += o.stats.rays
        stats.bound_rays += o.stats.bound_rays
    extra: dict = {}
    if search == "pruned":
        for key in ("bounded", "scored", "rounds", "bound_rays"):
            extra[key] = sum(o.extra[key] for o in outs)
        extra["k"] = outs[0].extra["k"]
    return sum(o.evaluated for o in outs), stats, extra


def per_rest_best(outs: list[Outcome]) -> list[float]:
    """Each pose's best grid score (-inf where nothing showed)."""
    return [float(np.max(o.scores)) if len(o.scores) else -math.inf for o in outs]


def with_rest(service: ScoringService, resting) -> ScoringService:
    """The same service (photo, renderer, timings, bar) under another resting pose."""
    return dataclasses.replace(service, resting=resting)
