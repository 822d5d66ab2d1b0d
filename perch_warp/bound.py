"""Upper bounds of candidates' scores from their silhouettes (the pruned search, kernels/bound.py).

bound(c) = top-α reduction of the photo's ceiling map at c's silhouette feature points >= score(c),
because every point's value is cos x gain - offset with cos <= 1 and gain >= 0, so at most
ceiling = gain - offset (the rarity, for the thesis's score; perch_warp.score_terms). Computing it
costs one ray per feature point (1/stride² of a render) and no features, so the search can bound every
candidate, score them best bound first, and stop once no bound reaches the k-th best score:
the same top-k as scoring all of them (thesis §5.1 asks for pruning and prioritisation).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .camera import Camera
from .hidden import HiddenPoints, hide
from .kernels.bound import rarity_at_hits
from .render import Renderer, point_layout
from .score import top_alpha_mean_device

# Scores are float32 cosines (which may exceed 1 by rounding) times rarity, averaged in float64:
# a candidate is dropped only when its bound is below the k-th best score by more than this.
BOUND_SLACK = 1e-5


def silhouette_points(
    renderer: Renderer,
    camera: Camera,
    R_m2c: np.ndarray,
    t_m2c_m: np.ndarray,
    boxes: np.ndarray,
    gboxes: np.ndarray,
    ceiling: wp.array,
    kernel_size: int,
    stride: int,
    hidden: HiddenPoints | None = None,
) -> tuple[wp.array, wp.array]:
    """The ceiling map (each point's largest possible value) at each candidate's silhouette feature
    points (NOT_ON_MASK off it, 0 beyond the photo)
    and the flat offsets (B + 1,), device arrays in the layout of FeatureScorer.score_points.
    Poses are model-to-camera (R (B, 3, 3), t (B, 3) metres); boxes are pixels, gboxes feature cells.
    The silhouette is the renderer's own (Renderer.silhouette): the mask kernel #2 will read. With
    `hidden` (perch_warp.hidden) the points another object covers nearer than the candidate's model origin
    are HIDDEN, exactly as kernel #2's values are marked."""
    layout = point_layout(boxes, gboxes, kernel_size, stride, renderer.device)
    hits = renderer.silhouette(camera, R_m2c, t_m2c_m, layout)
    with wp.ScopedDevice(renderer.device):
        out = wp.empty(layout.n_points, dtype=float)
        wp.launch(
            rarity_at_hits,
            dim=layout.n_points,
            inputs=[hits, layout, ceiling],
            outputs=[out],
        )
    if hidden is not None:
        hide(out, layout, t_m2c_m, hidden, 1)
    return out, layout.pt_off


def silhouette_bounds(
    renderer: Renderer,
    camera: Camera,
    R_m2c: np.ndarray,
    t_m2c_m: np.ndarray,
    boxes: np.ndarray,
    gboxes: np.ndarray,
    ceiling: wp.array,
    kernel_size: int,
    stride: int,
    alpha: float,
    shrink: float = 0.0,
    hidden: HiddenPoints | None = None,
) -> np.ndarray:
    """Upper bound (B,) float64 of each candidate's score; -inf where no feature point is on its
    silhouette, or every one is hidden (its score is then -inf too). With `hidden`: the bound of the
    score that leaves out what other objects hide (perch_warp.hidden), reduced as that score is."""
    vals, offsets = silhouette_points(
        renderer, camera, R_m2c, t_m2c_m, boxes, gboxes, ceiling, kernel_size, stride, hidden
    )
    beta = 0.0 if hidden is None else hidden.beta
    return top_alpha_mean_device(vals, offsets, alpha, shrink, beta=beta)[0].numpy()


def next_to_score(bounds_sorted: np.ndarray, start: int, threshold: float) -> int:
    """End of the run of candidates from `start` (sorted by bound, best first) that may still
    reach `threshold`, the k-th best score so far."""
    return start + int(np.searchsorted(-bounds_sorted[start:], -(threshold - BOUND_SLACK), side="right"))
