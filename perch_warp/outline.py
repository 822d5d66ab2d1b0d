"""The outline term (issue 17 (d)): does the photo show an edge where the candidate's outline runs?

A candidate's feature point on its outline (an on-mask point with a pixel off the mask within one
stride along an image axis; kernels/features.py `outline_at`) earns, beside its cosine,

    w * |e(b) . n|                (n: the outline's outward unit normal from the mask, b: the nearest
                                   off-mask pixel, e: the photo's normalised gradient at b)

so a pose whose silhouette follows the photo's edges gains over a look-alike patch whose edges run
elsewhere; the points' top-α reduction keeps tolerating an occluded part of the outline. The edge map
is the photo's grey-level gradient after a small Gaussian, normalised as g / (|g| + mean |g|): below 1
in length, unchanged by a global change of contrast or brightness, and a faint texture in a plain
photo does not saturate it as it would if divided by its own largest value.

Bound: |e(b) . n| <= |e(b)| and b lies within `reach` pixels of the point's pixel along one axis, so
the term is at most w * max |e| over the (2 reach + 1)^2 pixels around it (`edge_ceiling`), per feature
cell; with a shift d the outline pixel moves by d * stride with the cell, so the same cell-wise maximum
at the shifted cell bounds it (perch_warp.score_terms).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .image import check_rgb

EDGE_SIGMA_PX = 1.0  # Gaussian before the gradient: a 1-pixel edge spreads over ~3 pixels, noise averages out


def edge_map(image_rgb: np.ndarray, sigma_px: float = EDGE_SIGMA_PX) -> np.ndarray:
    """(H, W, 2) float32: the photo's normalised intensity gradient (d/dx, d/dy: +x right, +y down, per
    pixel) of its grey level (the mean of R, G, B in [0, 1]) smoothed by a Gaussian of sigma_px pixels,
    divided by (|g| + mean |g| over the photo); zeros for a flat photo."""
    grey = check_rgb(image_rgb).astype(np.float64).mean(axis=2) / 255.0
    if sigma_px > 0:
        grey = ndimage.gaussian_filter(grey, sigma_px, mode="nearest")
    gy, gx = np.gradient(grey)
    mag = np.hypot(gx, gy)
    scale = mag.mean()
    if scale <= 1e-12:
        return np.zeros(grey.shape + (2,), np.float32)
    denom = mag + scale
    return np.stack([gx / denom, gy / denom], axis=-1).astype(np.float32)


def edge_ceiling(edge: np.ndarray, rows: int, cols: int, kernel_size: int, stride: int) -> np.ndarray:
    """(rows, cols) float32: max |edge| over the pixels within `stride` of each feature cell's pixel
    (ks // 2 + stride gx, ks // 2 + stride gy) in x and in y, clipped to the photo: the most one outline
    point there can earn per unit of weight (module doc)."""
    mag = np.linalg.norm(np.asarray(edge, np.float64), axis=-1)
    pooled = ndimage.maximum_filter(mag, size=2 * stride + 1, mode="constant", cval=0.0)
    half = kernel_size // 2
    v = half + stride * np.arange(rows)
    u = half + stride * np.arange(cols)
    # A hair above the float64 maximum: kernel #2 forms |e . n| / |n| in float32.
    return (pooled[np.ix_(v, u)] * (1.0 + 1e-5)).astype(np.float32)
