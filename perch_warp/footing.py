"""The footing term (issue 17 (i), without a known table extent): does the candidate stand on the table?

The table plane continues in the image where no table is: across walls, monitors, the floor beyond
the table's edge, and behind other objects, where its place is hidden by them. An object can only
rest where the table top is, and then the table plane just in front of its footprint (between it and
the camera, where the object itself hides nothing) shows the table, unless something else stands
there. The term scores that, per candidate,

    footing(x, y) = top-half mean over the arc's points p of max(0, cos(I(p), B))

on an arc of the circle of radius r + MARGIN_M around the model origin's place (x, y) on the table
(r: the largest distance of the resting mesh's hull from its z axis, so the circle clears the footprint
at any yaw), FRONT_ARC_DEG wide and centred on the direction of the camera; I(p) is the photo's conv1
feature at the feature cell nearest p's pixel, B the photo's commonest appearance (the centroid of its
largest k-means cluster, as for the background term: usually the table). The top half tolerates a
neighbour standing in front of part of the arc. Points beyond the photo's feature grid or behind the
camera are left out; with none left the footing is 0.

The score becomes score + w * footing(x, y). The footing depends on (x, y) only, not on the render,
so it is added to the bound as it is: the pruned search stays exact and its bound as tight as before.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .score_terms import likeness_to_commonest
from .table import RestingPose, Table

FRONT_ARC_DEG = 120.0
ARC_POINTS = 9
MARGIN_M = 0.01


def footprint_radius_m(hull_m: np.ndarray, resting: RestingPose) -> float:
    """The largest distance (metres) of the resting mesh's hull points (model frame, metres) from the
    model origin's vertical axis on the table: the footprint's radius at any yaw."""
    p = np.asarray(hull_m, np.float64) @ resting.R_rest.T
    return float(np.hypot(p[:, 0], p[:, 1]).max())


def likeness_map(features: np.ndarray, labels: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """(rows, cols) float32: max(0, cos(I, B)) per feature cell, I the photo's features (rows * cols, C),
    B the centroid of the largest cluster of `labels` (rows * cols,) (score_terms.likeness_to_commonest)."""
    return likeness_to_commonest(features, labels).reshape(rows, cols).astype(np.float32)


def footing(
    table: Table,
    camera: Camera,
    likeness: np.ndarray,
    x_m: np.ndarray,
    y_m: np.ndarray,
    radius_m: float,
    kernel_size: int,
    stride: int,
) -> np.ndarray:
    """(N,) float64 in [0, 1]: the footing (module doc) of candidates at table-frame (x_m, y_m) (metres),
    the photo's likeness map on its feature grid (likeness_map)."""
    x = np.atleast_1d(np.asarray(x_m, np.float64))
    y = np.atleast_1d(np.asarray(y_m, np.float64))
    cam = table.camera_center_table_m
    towards = np.arctan2(cam[1] - y, cam[0] - x)
    half_arc = np.deg2rad(FRONT_ARC_DEG) / 2
    ang = towards[:, None] + np.linspace(-half_arc, half_arc, ARC_POINTS)[None, :]
    r = radius_m + MARGIN_M
    pts = np.stack([x[:, None] + r * np.cos(ang), y[:, None] + r * np.sin(ang), np.zeros_like(ang)], -1)
    pc = table.to_camera(pts)
    z = pc[..., 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = camera.fx * pc[..., 0] / zs + camera.cx
    v = camera.fy * pc[..., 1] / zs + camera.cy
    half = kernel_size // 2
    gx = np.rint((u - half) / stride)
    gy = np.rint((v - half) / stride)
    rows, cols = likeness.shape
    seen = front & (gx >= 0) & (gx < cols) & (gy >= 0) & (gy < rows)
    vals = np.where(
        seen, likeness[np.where(seen, gy, 0).astype(np.int64), np.where(seen, gx, 0).astype(np.int64)], -1.0
    )
    # The top half of the seen points: sort descending, unseen (-1) last.
    vals = -np.sort(-vals, axis=1)
    n_seen = seen.sum(axis=1)
    k = -(-n_seen // 2)  # ceil(n / 2)
    take = np.arange(ARC_POINTS)[None, :] < k[:, None]
    total = np.where(take, vals, 0.0).sum(axis=1)
    return np.divide(total, k, out=np.zeros(len(x)), where=k > 0)
