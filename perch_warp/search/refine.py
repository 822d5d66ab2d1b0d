"""The refinement below the grid (the best grid pose's cell searched at a finer resolution,
perch_warp.refine.cell_space) and the probe diagnostic that searches any pose's cell the same way."""

from __future__ import annotations

import math
import time

import numpy as np

from ..peaks import SEPARATION_STEPS, distinct_peaks, yaw_peaks
from ..refine import cell_space
from ..search_space import FULL_CIRCLE, SearchSpace
from . import exhaustive, pruned
from .base import Outcome, auto_search
from .scoring import ScoringService


def cell_search(grid_search: str, device: str) -> str:
    """The search a cell is searched with: the grid's (pruned or exhaustive: the same best); after
    coarse-to-fine, the one "auto" picks for the device."""
    return grid_search if grid_search in ("exhaustive", "pruned") else auto_search(device)


def best_in(service: ScoringService, cell: SearchSpace, wrap: bool, search: str):
    """The best pose (x_m, y_m, yaw_rad, score) of a small space searched whole by `search`
    ("exhaustive" or "pruned") on a quiet service, and the search's Outcome."""
    out: Outcome = (pruned.run if search == "pruned" else exhaustive.run)(service, cell)
    scores = out.scores
    i = int(np.argmax(scores))  # the first of equal maxima
    (x_i,), (y_i,), (yaw_i,) = cell.at(np.array([i]))
    # A cell may reach below 0 on the full circle: the same poses as below 2π, reported there.
    yaw_i = float(yaw_i) % (2 * math.pi) if wrap else float(yaw_i)
    return (float(x_i), float(y_i), yaw_i, float(scores[i])), out


def refine(service: ScoringService, space: SearchSpace, top: list, grid_search: str):
    """The best grid pose refined below the grid: the best of its cell at the fine resolution. It
    replaces the first of top [(x_m, y_m, yaw_rad, score)]; the runners-up stay. Timed as one "refine"
    stage (wall time); its rays are counted apart from the grid search's. Returns (top, info)."""
    cfg = service.config
    t = time.perf_counter()
    x0, y0, yaw0, s0 = top[0]
    cell = cell_space(space, x0, y0, yaw0, cfg.refine_xy_m, cfg.refine_yaw_rad, cfg.refine_cells)
    search = cell_search(grid_search, service.device)
    best, out = best_in(service.refining(), cell, space.full_circle, search)
    info = {
        "step_xy_m": cell.xy_step_m,
        "step_yaw_deg": math.degrees(cell.yaw_step_rad),
        "cell": cell.describe(),
        "search": search,
        "candidates": len(cell),
        "evaluated": int(np.isfinite(out.scores).sum()),
        "from": {"x_m": x0, "y_m": y0, "yaw_deg": math.degrees(yaw0), "score": s0},
        "score_gain": best[3] - s0,
        "rays": out.stats.rays,
    }
    service.lap("refine", t)
    return [best, *(c for c in top[1:] if not same_pose(c, best))], info


def same_pose(a: tuple, b: tuple) -> bool:
    """Poses (x_m, y_m, yaw_rad, ...) a and b are the same pose (to 1e-9 in each coordinate)."""
    return all(abs(a[j] - b[j]) < 1e-9 for j in range(3))


def probe(service: ScoringService, space: SearchSpace, pose: tuple[float, float, float], grid_search: str) -> dict:
    """The best of pose's cell at the refinement's resolution (not cut to the space), for analysis:
    it never changes the answer, and its cost is not the search's."""
    cfg = service.config
    everywhere = SearchSpace((-1e6, 1e6), (-1e6, 1e6), space.xy_step_m, FULL_CIRCLE, space.yaw_step_rad)
    x, y, yaw = (float(v) for v in pose)
    cell = cell_space(everywhere, x, y, yaw, cfg.refine_xy_m, cfg.refine_yaw_rad, cfg.refine_cells)
    search = cell_search(grid_search, service.device)
    (bx, by, byaw, score), _ = best_in(service.refining(), cell, True, search)
    return {"x_m": bx, "y_m": by, "yaw_rad": byaw, "score": score, "candidates": len(cell), "at": [x, y, yaw]}


def place_yaws(service: ScoringService, space: SearchSpace, place: tuple, m: int) -> list[tuple]:
    """Grid poses (x_m, y_m, yaw_rad, score) to refine at the place of grid pose `place`: the pose itself,
    then up to m - 1 more yaw peaks there (perch_warp.peaks.yaw_peaks over every grid yaw of the place,
    scored on a quiet service: on the pruned grid most of a place's yaws were never scored)."""
    if m <= 1:
        return [place]
    x, y, yaw0, _ = place
    yaws = space.axes()[2]
    scores = service.quiet().score((np.full(len(yaws), x), np.full(len(yaws), y), yaws))
    first = int(np.argmin(np.abs(yaws - yaw0)))
    idx = yaw_peaks(scores, m, space.full_circle, first)
    return [place, *((x, y, float(yaws[i]), float(scores[i])) for i in idx[1:])]


def refine_place(service: ScoringService, space: SearchSpace, place: tuple, grid_search: str, refine_fn=None):
    """The best of `refine` over place_yaws(place): (refined pose, that refinement's info with
    "yaws_deg": the grid yaws refined at this place). refine_fn, if given, is called instead of `refine`
    with the same arguments (tools/peaks_check.py: a cache of refinements shared by its strategies)."""
    best = None
    poses = place_yaws(service, space, place, service.config.refine_yaws)
    for pose in poses:
        out, info = (refine_fn or refine)(service, space, [pose], grid_search)
        if best is None or out[0][3] > best[0][3]:  # ties to the place's own grid best
            best = (out[0], info)
    return best[0], {**best[1], "yaws_deg": [math.degrees(p[2]) for p in poses]}


def refine_peaks(service: ScoringService, space: SearchSpace, top: list, grid_search: str, refine_fn=None):
    """`refine_place` on each of the grid's best `refine_peaks` distinct peaks (perch_warp.peaks: top holds
    the best candidate of each of the best locations; peaks are locations apart); the best refined pose
    first, then the other peaks' refined poses, then the runners-up. With one peak and one yaw, `refine`
    itself. `refine_fn`: refine_place's, for the peaks' refinements (tools/peaks_replay.py: a refinement
    it already made). Returns (top, info); info["peaks"] lists each peak."""
    cfg = service.config
    if cfg.refine_peaks <= 1 and cfg.refine_yaws <= 1:
        return refine(service, space, top, grid_search)
    idx, refined, order = refine_each(
        top, cfg.refine_peaks, space, lambda i: refine_place(service, space, top[i], grid_search, refine_fn)
    )
    best_info = {**refined[order[0]][1], "peaks": [peak_summary(c, i) for c, i in refined]}
    seen = {tuple(top[i][:3]) for i in idx}
    return [*(refined[n][0] for n in order), *(c for c in top if tuple(c[:3]) not in seen)], best_info


def refine_each(top: list, n: int, space: SearchSpace, refine_at):
    """refine_at(i) -> (refined pose, info), refine_place's pair, at each of top's best n distinct peaks
    (perch_warp.peaks.distinct_peaks: top holds the best candidate of each of the best locations, sorted
    best first; peaks are locations apart). Returns (the peaks' indices in top, their refinements, the
    refinements' order best first; stable: ties to the better grid peak)."""
    idx = distinct_peaks([c[:4] for c in top], n, SEPARATION_STEPS * space.xy_step_m)
    refined = [refine_at(i) for i in idx]
    order = sorted(range(len(refined)), key=lambda m: -refined[m][0][3])
    return idx, refined, order


def peak_summary(pose: tuple, info: dict) -> dict:
    """A refined peak as info["peaks"] lists it: where its refinement started, the grid yaws refined
    there and the refined pose (x_m, y_m, yaw_rad, score, ...)."""
    return {
        "from": info["from"],
        "yaws_deg": info["yaws_deg"],
        "x_m": pose[0],
        "y_m": pose[1],
        "yaw_rad": pose[2],
        "score": pose[3],
    }
