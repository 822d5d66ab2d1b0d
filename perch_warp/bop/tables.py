"""Table frames of BOP images: the camera entry's cam_R_w2c/cam_t_w2c, else a RANSAC plane fit to the
depth image (metres, camera frame)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import PerchError
from ..table import Table
from .inout import image_path, read_depth_mm


def depth_points_m(depth_mm: np.ndarray, camera: Camera, stride: int = 4) -> np.ndarray:
    """Back-project every `stride`-th valid depth pixel to camera-frame points (M, 3), metres."""
    if depth_mm.shape != (camera.height, camera.width):
        raise PerchError(
            f"depth image is {depth_mm.shape[1]}x{depth_mm.shape[0]} but the camera is {camera.width}x{camera.height}"
        )
    v, u = np.mgrid[0 : camera.height : stride, 0 : camera.width : stride]
    z = depth_mm[v, u].astype(np.float64) / 1000.0
    ok = z > 0
    u, v, z = u[ok], v[ok], z[ok]
    return np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], -1)


def fit_plane_ransac(
    points_m: np.ndarray, threshold_m: float = 0.01, iterations: int = 500, seed: int = 0
) -> tuple[np.ndarray, float, np.ndarray]:
    """The plane n . X + d = 0 with most points within `threshold_m`, refined by least squares on them.

    Returns (unit normal n, d metres, inlier mask). n is oriented so that d > 0, i.e.
    the camera origin lies on the normal's side (the side the camera sees). Fixed
    `seed`: the same depth image always gives the same plane.
    """
    P = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if len(P) < 3:
        raise PerchError(f"plane fit needs at least 3 depth points, got {len(P)}")
    rng = np.random.default_rng(seed)
    best_count, best = -1, None
    for _ in range(iterations):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        count = int(np.count_nonzero(np.abs(P @ n - n @ a) < threshold_m))
        if count > best_count:
            best_count, best = count, (n, -float(n @ a))
    if best is None:
        raise PerchError("plane fit failed: the depth points are collinear")
    n, d = best
    inliers = np.abs(P @ n + d) < threshold_m
    # Total least squares on the inliers: the normal is the smallest principal axis.
    Q = P[inliers]
    centroid = Q.mean(0)
    n = np.linalg.svd(Q - centroid, full_matrices=False)[2][-1]
    d = -float(n @ centroid)
    inliers = np.abs(P @ n + d) < threshold_m
    if d < 0:
        n, d = -n, -d
    return n, d, inliers


def table_from_plane(normal_c: np.ndarray, d_m: float) -> Table:
    """A table frame on the plane n . X + d = 0 (camera frame, metres), +z = n towards the camera.

    Axes chosen deterministically as in the shared ycbv frames' `cam_R_w2c`: x is the
    camera's x axis projected onto the plane, y = z x x; the origin is where the
    optical axis meets the plane (the foot of the perpendicular from the camera
    when the optical axis runs parallel to it).
    """
    n = np.asarray(normal_c, dtype=np.float64).reshape(3)
    n = n / np.linalg.norm(n)
    if d_m < 0:
        n, d_m = -n, -d_m
    x = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(x) < 1e-6:  # camera x along the normal: fall back to camera y
        x = np.array([0.0, 1.0, 0.0]) - n[1] * n
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    R = np.stack([x, y, n], axis=1)  # columns: table axes in camera frame
    if abs(n[2]) > 1e-6 and -d_m / n[2] > 0:
        origin = np.array([0.0, 0.0, -d_m / n[2]])
    else:
        origin = -d_m * n
    return Table(R, origin)


def table_from_depth(depth_path: str | Path, camera: Camera, depth_scale: float, threshold_m: float = 0.01) -> Table:
    """RANSAC plane fit of a BOP depth image: the dominant plane taken as the table top."""
    depth_mm = read_depth_mm(depth_path, depth_scale)
    try:
        pts = depth_points_m(depth_mm, camera)
        n, d, inliers = fit_plane_ransac(pts, threshold_m=threshold_m)
        return table_from_plane(n, d)
    except PerchError as e:
        raise PerchError(f"{depth_path}: {e}") from None


def table_source_for(entry: dict, scene_dir: Path, im_id: int, source: str | Path, how: str = "auto") -> str:
    """Which table frame an image will use: "cam_R_w2c" or "depth RANSAC"; PerchError naming what is missing.

    how: "auto" (the camera entry's cam_R_w2c/cam_t_w2c, else a plane fit to the depth
    image), "w2c" or "depth" to insist on one.
    """
    if how not in ("auto", "w2c", "depth"):
        raise PerchError(f"table source must be auto, w2c or depth, got {how!r}")
    if how in ("auto", "w2c") and "cam_R_w2c" in entry and "cam_t_w2c" in entry:
        return "cam_R_w2c"
    if how == "w2c":
        raise PerchError(f"{source}: image {im_id} has no cam_R_w2c/cam_t_w2c (the table frame)")
    depth = image_path(scene_dir, im_id, "depth")
    if depth is None or "depth_scale" not in entry:
        missing = "depth image" if depth is None else f"'depth_scale' in {source}"
        raise PerchError(
            f"no table frame for scene {scene_dir.name} image {im_id}: {source} has no cam_R_w2c/cam_t_w2c "
            f"and the {missing} for a plane fit is missing ({scene_dir / 'depth' / f'{im_id:06d}.png'})"
        )
    return "depth RANSAC"


def table_for_image(
    entry: dict, scene_dir: Path, im_id: int, camera: Camera, source: str | Path, how: str = "auto"
) -> tuple[Table, str]:
    """The table frame for one image and where it came from (see `table_source_for`)."""
    kind = table_source_for(entry, scene_dir, im_id, source, how)
    if kind == "cam_R_w2c":
        return Table.from_entry(entry, source=f"{source} image {im_id}"), kind
    depth = image_path(scene_dir, im_id, "depth")
    return table_from_depth(depth, camera, float(entry["depth_scale"])), kind
