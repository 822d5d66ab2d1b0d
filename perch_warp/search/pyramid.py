"""The coarse-to-fine (pyramid) search on the space's own grid: a coarse lattice, then around the best
`beam` candidates ever finer lattices down to the grid step, then hill-climbing on the grid until the
best `beam` stop changing. Every grid point is scored at most once."""

from __future__ import annotations

import math

import numpy as np

from ..search_space import SearchSpace
from .base import Outcome, kth_largest
from .pruned import best_first
from .scoring import PoseSource, ScoringService, SearchStats


class _Pyramid:
    """The grid points scored so far (memo: flat index -> score) and those ruled out by their bounds."""

    def __init__(self, service: ScoringService, space: SearchSpace, stats: SearchStats) -> None:
        self.service, self.space, self.stats = service, space, stats
        self.cfg = service.config
        self.nx, self.ny, self.nk = (len(a) for a in space.axes())
        self.memo: dict[int, float] = {}
        # Grid points whose silhouette bound fell below the beam's threshold: they can never enter
        # the beam (the threshold only rises as memo grows), so they are neither scored nor asked again.
        self.ruled_out: set[int] = set()
        self.k_beam = max(self.cfg.beam, self.cfg.top_k)

    def run(self, ijk: np.ndarray) -> None:
        """Score the grid points ijk (N, 3) not yet known (out-of-grid ones dropped, yaw wrapped on a full circle)."""
        nx, ny, nk = self.nx, self.ny, self.nk
        i, j, k = ijk.T
        k = k % nk if self.space.full_circle else k
        ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny) & (k >= 0) & (k < nk)
        flat = np.unique((i[ok] * ny + j[ok]) * nk + k[ok])
        flat = np.array([f for f in flat.tolist() if f not in self.memo and f not in self.ruled_out], dtype=np.int64)
        if len(flat) == 0:
            return
        poses = PoseSource.of_arrays(*self.space.at(flat))
        if not self.cfg.pyramid_bounds:
            sc = self.service.score(poses, self.stats)
            self.memo.update(zip(flat.tolist(), sc.tolist(), strict=True))
            return
        sc = np.full(len(flat), -np.inf)
        known = np.fromiter(self.memo.values(), dtype=np.float64, count=len(self.memo))

        def kth_best(scored: np.ndarray) -> float:
            return kth_largest(np.concatenate([known, sc[scored]]), self.k_beam)

        bf = best_first(self.service, poses, sc, kth_best, self.stats)
        # Memoised: the scored, and those whose score is -inf because no feature point shows (as
        # without bounds). Ruled out: a finite bound below the threshold, so a score below it too.
        dropped = np.isfinite(bf.bounds)
        dropped[bf.scored] = False
        self.memo.update(zip(flat[~dropped].tolist(), sc[~dropped].tolist(), strict=True))
        self.ruled_out.update(flat[dropped].tolist())

    def best(self) -> np.ndarray:
        """Grid indices (beam, 3) of the best `beam` scored so far, ties to the lower flat index."""
        memo = self.memo
        flat = np.fromiter(memo.keys(), dtype=np.int64, count=len(memo))
        sc = np.fromiter(memo.values(), dtype=np.float64, count=len(memo))
        top = flat[np.lexsort((flat, -sc))[: self.cfg.beam]]
        ii, rest = np.divmod(top, self.ny * self.nk)
        jj, kk = np.divmod(rest, self.nk)
        return np.stack([ii, jj, kk], -1)

    def level(self, step: tuple[int, int], evaluated: int) -> dict:
        return {
            "step_xy_m": step[0] * self.space.xy_step_m,
            "step_yaw_deg": math.degrees(step[1] * self.space.yaw_step_rad),
            "evaluated": evaluated,
        }


def _around(centres: np.ndarray, reach: tuple[int, int], step: tuple[int, int]) -> np.ndarray:
    dxy = np.arange(-reach[0], reach[0] + 1, step[0])
    dk = np.arange(-reach[1], reach[1] + 1, step[1])
    D = np.stack(np.meshgrid(dxy, dxy, dk, indexing="ij"), -1).reshape(-1, 3)
    return (centres[:, None, :] + D[None]).reshape(-1, 3)


def _lattice(n: int, f: int, closed: bool) -> np.ndarray:
    a = np.arange(0, n, f)
    return np.union1d(a, [n - 1]) if closed else a


def run(service: ScoringService, space: SearchSpace) -> Outcome:
    """Scores of the grid points visited (flat indices into the space's order, ascending) and the levels."""
    cfg = service.config
    p = _Pyramid(service, space, SearchStats())
    f_xy = max(1, round(cfg.coarse_xy_m / space.xy_step_m))
    f_yaw = max(1, round(cfg.coarse_yaw_rad / space.yaw_step_rad))
    steps = [(f_xy, f_yaw)]
    while steps[-1] != (1, 1):
        steps.append((max(1, steps[-1][0] // 2), max(1, steps[-1][1] // 2)))
    li, lj = _lattice(p.nx, f_xy, True), _lattice(p.ny, f_xy, True)
    lk = _lattice(p.nk, f_yaw, not space.full_circle)
    p.run(np.stack(np.meshgrid(li, lj, lk, indexing="ij"), -1).reshape(-1, 3))
    levels = [p.level(steps[0], len(p.memo))]
    for prev, step in zip(steps, steps[1:], strict=False):
        n0 = len(p.memo)
        p.run(_around(p.best(), prev, step))
        levels.append(p.level(step, len(p.memo) - n0))
    n0 = len(p.memo)
    for _ in range(cfg.max_polish):
        before = len(p.memo)
        p.run(_around(p.best(), (1, 1), (1, 1)))
        if len(p.memo) == before:
            break
    levels.append({"polish_evaluated": len(p.memo) - n0})
    flat = np.fromiter(p.memo.keys(), dtype=np.int64, count=len(p.memo))
    order = np.argsort(flat)
    sc = np.fromiter(p.memo.values(), dtype=np.float64, count=len(p.memo))[order]
    return Outcome(sc, len(flat), p.stats, flat=flat[order], extra={"levels": levels})
