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


def hide(values: wp.array, pts: PointLayout, distance_m: np.ndarray, hidden: HiddenPoints, n_blocks: int) -> None:
    """Mark HIDDEN, in place, the values (n_blocks blocks of pts' points, as kernel #2 lays them out) of
    points the occluder map covers nearer than their candidate (distance_m (B,): each candidate's model
    origin's distance from the camera, metres)."""
    with wp.ScopedDevice(values.device):
        dist = wp.array(np.asarray(distance_m, dtype=np.float32), dtype=float)
        wp.launch(hide_points, dim=pts.n_points, inputs=[pts, hidden.near_m, dist, int(n_blocks)], outputs=[values])
