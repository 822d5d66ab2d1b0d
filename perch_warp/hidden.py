"""What other objects hide: their silhouettes in the photo, so a candidate is not scored where it is covered.

With several objects in one photo, a target that stands behind another shows only part of itself, and the
plain top-α mean then compares the nearer object's pixels with the target's render: a look-alike in full
view wins (docs/accuracy.md, stop 57). Given where the other objects are (their answers of a first pass,
perch_warp.objects), the occluder map holds, per feature-grid cell, the camera distance (metres) of the
nearest of them whose rendered silhouette covers the cell's pixel (+inf where none). Kernel #2's values
and the bound's ceilings at a candidate's points where the map is nearer than the candidate's model
origin are marked HIDDEN (kernels/hidden.py); the reduction (kernels/reduce.py) averages the best
α share of max(V, ceil(β N)) points over the V visible ones of N (β = `beta`). Every visible value is at
most its ceiling and the reduction never falls when a visible value rises, so the silhouette bound
marked the same way stays an upper bound.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import warp as wp

from .errors import PerchError
from .kernels.features import PointLayout
from .kernels.hidden import hide_points

# The share of a candidate's points that k counts at least when some are hidden: chosen on the development
# set (docs/accuracy.md, stop 57: beta 0 lets poses almost wholly behind another answer win on a few
# points; beta 1 counts hidden points as zeros, the plain score's failure).
DEFAULT_BETA = 0.25


@dataclass(frozen=True)
class HiddenPoints:
    """The occluder map of one photo for one object, on the device: near_m (rows, cols) float32, the
    nearest occluder's distance from the camera per feature-grid cell (metres, +inf where none), and beta."""

    near_m: wp.array
    beta: float
    occluders: int  # how many objects it was made from (for the result's record)

    def to_dict(self) -> dict:
        covered = int(np.isfinite(self.near_m.numpy()).sum())
        return {"occluders": self.occluders, "beta": self.beta, "cells_covered": covered}

    @cached_property
    def _minima(self) -> BoxMinima:
        return BoxMinima(self.near_m.numpy())

    def untouched(self, gboxes: np.ndarray, t_m2c_m: np.ndarray) -> np.ndarray:
        """(N,) bool: candidates none of whose feature points the map can hide. gboxes (N, 4) are their
        feature-grid boxes (gx0, gy0, gw, gh: every point lies in its box), t_m2c_m (N, 3) their
        model-to-camera translations (metres), as `hide` takes them. True where no cell of the box (within
        the grid) holds an occluder nearer than the candidate (`origin_distance_m`): the kernel's own
        float32 test over a superset of the points, so an untouched candidate's score is the plain score
        (kernels/reduce.py)."""
        return ~(self._minima.least(gboxes) < origin_distance_m(t_m2c_m))


class BoxMinima:
    """The least value of a 2-D map over axis-aligned boxes, each in O(1) (a sparse table: minima over
    every 2^a x 2^b block, the four blocks that cover a box overlap inside it)."""

    def __init__(self, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float32)
        if v.ndim != 2:
            raise PerchError(f"BoxMinima takes a 2-D map, got shape {v.shape}")
        self.shape = v.shape
        rows = [v]  # rows[a][r, c] = min of v[r : r + 2^a, c] (+inf past the edge)
        while (2 << (len(rows) - 1)) <= v.shape[0]:
            prev, h = rows[-1], 1 << (len(rows) - 1)
            nxt = np.full_like(prev, np.inf)
            nxt[:-h] = np.minimum(prev[:-h], prev[h:])
            rows.append(nxt)
        table = []  # table[a][b][r, c] = min of v[r : r + 2^a, c : c + 2^b]
        for r in rows:
            cols = [r]
            while (2 << (len(cols) - 1)) <= v.shape[1]:
                prev, w = cols[-1], 1 << (len(cols) - 1)
                nxt = np.full_like(prev, np.inf)
                nxt[:, :-w] = np.minimum(prev[:, :-w], prev[:, w:])
                cols.append(nxt)
            table.append(np.stack(cols))
        self.table = np.stack(table)  # (A, B, rows, cols)

    def least(self, boxes: np.ndarray) -> np.ndarray:
        """(N,) float32: the least value within each box (x0, y0, w, h) cut to the map; +inf where the
        cut box is empty."""
        b = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
        n_rows, n_cols = self.shape
        x0, y0 = np.clip(b[:, 0], 0, n_cols), np.clip(b[:, 1], 0, n_rows)
        x1, y1 = np.clip(b[:, 0] + b[:, 2], 0, n_cols), np.clip(b[:, 1] + b[:, 3], 0, n_rows)
        out = np.full(len(b), np.inf, dtype=np.float32)
        ok = (x1 > x0) & (y1 > y0)
        x0, y0, x1, y1 = x0[ok], y0[ok], x1[ok], y1[ok]
        a = np.frexp((y1 - y0).astype(np.float64))[1] - 1  # floor(log2 h), exactly
        c = np.frexp((x1 - x0).astype(np.float64))[1] - 1
        ya, xc = y1 - (1 << a), x1 - (1 << c)
        t = self.table
        out[ok] = np.minimum(np.minimum(t[a, c, y0, x0], t[a, c, ya, x0]), np.minimum(t[a, c, y0, xc], t[a, c, ya, xc]))
        return out


def occluder_map(
    silhouettes: Sequence[tuple[np.ndarray, float]], rows: int, cols: int, kernel_size: int, stride: int
) -> np.ndarray:
    """(rows, cols) float32: per feature-grid cell (pixel (ks // 2 + stride gx, ks // 2 + stride gy), as
    kernels/features.py PointLayout places points) the least distance (metres) among the silhouettes
    (mask (H, W) bool in the photo, the object's distance from the camera) covering that pixel; +inf
    where none does."""
    half = kernel_size // 2
    v = half + stride * np.arange(rows)
    u = half + stride * np.arange(cols)
    out = np.full((rows, cols), np.inf, dtype=np.float32)
    for mask, distance_m in silhouettes:
        if not distance_m > 0.0:
            raise PerchError(f"an occluder's distance from the camera must be positive, got {distance_m}")
        covered = np.asarray(mask, dtype=bool)[np.ix_(v, u)]
        out[covered] = np.minimum(out[covered], np.float32(distance_m))
    return out


def hidden_points(near_m: np.ndarray, beta: float, occluders: int, device: str) -> HiddenPoints:
    """The HiddenPoints of an occluder map (occluder_map's, on the photo's feature grid) on `device`."""
    if not 0.0 <= beta <= 1.0:
        raise PerchError(f"beta (the share of points counted when some are hidden) must be in [0, 1], got {beta}")
    near = np.ascontiguousarray(near_m, dtype=np.float32)
    if near.ndim != 2:
        raise PerchError(f"the occluder map must be 2-D (the feature grid), got shape {near.shape}")
    return HiddenPoints(wp.array(near, dtype=float, device=device), float(beta), int(occluders))


def origin_distance_m(t_m2c_m: np.ndarray) -> np.ndarray:
    """(N,) float32: each candidate's model origin's distance from the camera (metres), from its
    model-to-camera translation t_m2c_m (N, 3) metres: the distance the occluder map is compared with,
    by `hide` and `HiddenPoints.untouched` alike."""
    t = np.asarray(t_m2c_m, dtype=np.float64).reshape(-1, 3)
    return np.linalg.norm(t, axis=1).astype(np.float32)


def hide(values: wp.array, pts: PointLayout, t_m2c_m: np.ndarray, hidden: HiddenPoints, n_blocks: int) -> None:
    """Mark HIDDEN, in place, the values (n_blocks blocks of pts' points, as kernel #2 lays them out) of
    points the occluder map covers nearer than their candidate (t_m2c_m (B, 3): each candidate's
    model-to-camera translation, metres; compared by `origin_distance_m`)."""
    with wp.ScopedDevice(values.device):
        dist = wp.array(origin_distance_m(t_m2c_m), dtype=float)
        wp.launch(hide_points, dim=pts.n_points, inputs=[pts, hidden.near_m, dist, int(n_blocks)], outputs=[values])
