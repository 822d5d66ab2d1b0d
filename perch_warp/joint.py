"""The joint step of a several-object search: one answer per object, the answers consistent.

Each object's own search gives its best distinct peaks, each refined (search/refine.refine_peaks), so
their scores compare. Two answers *conflict* when

- their footprints on the table overlap by more than `overlap_m` (default 1 cm) and so do their heights
  above it: two objects cannot occupy the same space, and the tolerance lets neighbours touch although
  each estimate may be a grid step off. A footprint is the convex hull of the posed mesh's hull points
  projected on the table plane (table frame, metres), its height their z range; an object standing on
  another (a can on a lying box, as in YCB-Video's frame 000002 under the ground truth's resting
  poses) shares footprint but not height;
- or the farther one is hidden behind the nearer one over more than 1 - α of its silhouette: its
  score, the mean of its best α share of points, would then be made of pixels the nearer object
  explains (one image region explained twice). "Nearer" compares the objects' centres' distances from
  the camera: objects on a table that do not intersect rarely interleave.

The step chooses one peak per object with the fewest conflicts, then the largest sum of scores:
exactly, by enumerating every combination while they number at most EXACT_MAX; greedily beyond
(objects by their best score, each taking its best peak that conflicts with none chosen so far, else
its peak with the fewest such conflicts). The result says which.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .errors import PerchError
from .table import Table

EXACT_MAX = 100_000  # combinations enumerated exactly; beyond, the greedy choice
DEFAULT_OVERLAP_M = 0.01
DEFAULT_PEAKS = 4


@dataclass
class Peak:
    """One object's candidate answer as the joint step sees it."""

    score: float
    footprint_m: np.ndarray  # (P, 2) convex polygon on the table, table frame, metres, counter-clockwise
    mask: np.ndarray  # (H, W) bool: the rendered silhouette in the photo
    distance_m: float  # the object's centre from the camera, metres
    z_m: tuple[float, float] = (-math.inf, math.inf)  # lowest and highest point above the table, metres


@dataclass
class JointChoice:
    """The peak chosen per object, how, and what conflicts remain (none where a consistent choice exists)."""

    picks: list[int]
    method: str  # "exact" or "greedy"
    combinations: int  # how many combinations there were (all enumerated when exact)
    total_score: float
    conflicts: list[tuple[int, int, str]] = field(default_factory=list)  # (object i, object j, why)
    # Why each moved object left its own best: (object i, object j, why) for every chosen answer j that
    # i's own best (peak 0) conflicts with.
    moved: list[tuple[int, int, str]] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "combinations": self.combinations,
            "picks": self.picks,
            "total_score": self.total_score,
            "conflicts": [{"objects": [i, j], "why": why} for i, j, why in self.conflicts],
            "moved": [{"object": i, "by": j, "why": why} for i, j, why in self.moved],
        }

    def moved_by(self, i: int) -> list[tuple[int, str]]:
        """(object j, why) for each chosen answer that object i's own best conflicts with."""
        return [(j, why) for k, j, why in self.moved if k == i]


def joint_config(config, peaks: int):
    """EngineConfig `config` with at least `peaks` distinct peaks refined and reported (several objects)."""
    if not config.refine:
        raise PerchError("several objects need their peaks refined: drop --no-refine")
    return dataclasses.replace(config, refine_peaks=max(config.refine_peaks, peaks), top_k=max(config.top_k, peaks))


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """Convex hull (P, 2) of 2-D points, counter-clockwise, no repeated or collinear vertices
    (Andrew's monotone chain)."""
    pts = sorted({(float(x), float(y)) for x, y in np.asarray(points, dtype=np.float64)})
    if len(pts) <= 2:
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def half(seq):
        out: list = []
        for p in seq:
            while len(out) >= 2 and _cross(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(half(pts) + half(reversed(pts)), dtype=np.float64)


def _cross(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def footprint(table: Table, T_m2c: np.ndarray, hull_m: np.ndarray) -> np.ndarray:
    """The object's footprint on the table: its hull points (model frame, metres) posed by T_m2c (model ->
    camera), taken to the table frame and projected on the plane z = 0; a convex polygon (P, 2), metres."""
    return convex_hull_2d(_in_table(table, T_m2c, hull_m)[:, :2])


def height_range(table: Table, T_m2c: np.ndarray, hull_m: np.ndarray) -> tuple[float, float]:
    """The posed object's lowest and highest point above the table top (table frame z, metres)."""
    z = _in_table(table, T_m2c, hull_m)[:, 2]
    return float(z.min()), float(z.max())


def _in_table(table: Table, T_m2c: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """Model-frame points posed by T_m2c (model -> camera), in the table frame (metres)."""
    T = np.asarray(T_m2c, dtype=np.float64)
    p_cam = np.asarray(points_m, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    return (p_cam - table.t_t2c_m) @ table.R_t2c  # R^T (p - t) for row vectors


def footprint_overlap_m(a: np.ndarray, b: np.ndarray) -> float:
    """How far two convex polygons (P, 2) overlap (metres): the shortest distance one must move to part
    them (the separating axis theorem: the smallest push that separates their projections on the normals
    of their edges); zero or less when they do not overlap."""
    depth = math.inf
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
        lengths = np.linalg.norm(normals, axis=1)
        normals = normals[lengths > 0] / lengths[lengths > 0, None]
        pa, pb = a @ normals.T, b @ normals.T
        overlap = np.minimum(pa.max(0) - pb.min(0), pb.max(0) - pa.min(0))  # push b along +n or along -n
        depth = min(depth, float(overlap.min()))
    return depth


def hidden_share(near_mask: np.ndarray, far_mask: np.ndarray) -> float:
    """The share of the farther object's silhouette that the nearer one covers (0 for an empty one)."""
    n = int(np.count_nonzero(far_mask))
    return int(np.count_nonzero(near_mask & far_mask)) / n if n else 0.0


def conflict(
    p: Peak, q: Peak, alpha: float, overlap_m: float = DEFAULT_OVERLAP_M, hidden_rule: bool = True
) -> str | None:
    """Why answers p and q cannot both hold (module doc), or None; footprints only without `hidden_rule`
    (scores that leave out what another object hides: perch_warp.hidden)."""
    depth = footprint_overlap_m(p.footprint_m, q.footprint_m)
    height = min(p.z_m[1], q.z_m[1]) - max(p.z_m[0], q.z_m[0])
    if depth > overlap_m and height > overlap_m:
        return f"footprints overlap by {depth * 100:.1f} cm"
    if not hidden_rule:
        return None
    near, far = (p, q) if p.distance_m <= q.distance_m else (q, p)
    hidden = hidden_share(near.mask, far.mask)
    if hidden > 1.0 - alpha:
        return f"the farther is {hidden * 100:.0f} % hidden behind the nearer (more than 1 - alpha)"
    return None


def choose(
    scores: Sequence[Sequence[float]],
    clash: Callable[[int, int, int, int], str | None],
    exact_max: int = EXACT_MAX,
) -> JointChoice:
    """One peak per object (scores[i][a]: object i's peak a), the fewest conflicting pairs and then the
    largest total score; clash(i, a, j, b) says why object i's peak a and object j's peak b conflict
    (i < j), or None. Exact while the combinations number at most exact_max (ties go to the first combination in
    itertools.product order), else greedy (module doc)."""
    n = len(scores)
    if n == 0 or any(len(s) == 0 for s in scores):
        raise ValueError("every object needs at least one peak")
    table = _clash_table(scores, clash)
    combinations = math.prod(len(s) for s in scores)
    if combinations <= exact_max:
        picks, method = _exact(scores, table), "exact"
    else:
        picks, method = _greedy(scores, table), "greedy"
    total = float(sum(scores[i][a] for i, a in enumerate(picks)))
    left = [(i, j, why) for i in range(n) for j in range(i + 1, n) if (why := table[i][j][picks[i]][picks[j]])]
    moved = [
        (i, j, why)
        for i in range(n)
        if picks[i] != 0
        for j in range(n)
        if j != i and (why := _pair(table, i, 0, j, picks[j]))
    ]
    return JointChoice(list(picks), method, combinations, total, left, moved)


def _clash_table(scores, clash) -> list:
    """table[i][j][a][b] for i < j: why object i's peak a conflicts with object j's peak b, or None."""
    n = len(scores)
    table: list = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            table[i][j] = [[clash(i, a, j, b) for b in range(len(scores[j]))] for a in range(len(scores[i]))]
    return table


def _conflicts(table, picks: Sequence[int], upto: int | None = None) -> int:
    n = len(picks) if upto is None else upto
    return sum(bool(table[i][j][picks[i]][picks[j]]) for i in range(n) for j in range(i + 1, n))


def _exact(scores, table) -> tuple[int, ...]:
    best, best_key = None, None
    for picks in itertools.product(*(range(len(s)) for s in scores)):
        key = (_conflicts(table, picks), -sum(scores[i][a] for i, a in enumerate(picks)))
        if best_key is None or key < best_key:
            best, best_key = picks, key
    return best


def _pair(table, i: int, a: int, j: int, b: int):
    """Why object i's peak a and object j's peak b conflict (either order), or None."""
    return table[i][j][a][b] if i < j else table[j][i][b][a]


def _greedy(scores, table) -> list[int]:
    order = sorted(range(len(scores)), key=lambda i: -max(scores[i]))  # stable: ties to the earlier object
    picks: dict[int, int] = {}
    for i in order:
        by_score = sorted(range(len(scores[i])), key=lambda a, i=i: -scores[i][a])
        # min keeps the first, best-scoring, of the peaks with equally few conflicts
        picks[i] = min(by_score, key=lambda a, i=i: sum(bool(_pair(table, i, a, j, b)) for j, b in picks.items()))
    return [picks[i] for i in range(len(scores))]
