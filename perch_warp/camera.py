"""Pinhole camera intrinsics (OpenCV/BOP convention: pixel (u, v) centres are integers)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import PerchError


@dataclass(frozen=True)
class Camera:
    """Intrinsics `K` (3x3, pixels) and image size.

    A point X_c (camera frame, any length unit, +z forward, +y down) projects to
    u = fx X/Z + cx, v = fy Y/Z + cy; pixel (u, v) covers [u-0.5, u+0.5).
    """

    K: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise PerchError(f"camera intrinsics must be a finite 3x3 matrix, got {np.asarray(self.K).tolist()}")
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if fx <= 0 or fy <= 0:
            raise PerchError(f"camera focal lengths must be positive, got fx={fx}, fy={fy}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise PerchError(f"camera K must be upper triangular with K[2,2] = 1, got {K.tolist()}")
        if self.width <= 0 or self.height <= 0:
            raise PerchError(f"image size must be positive, got {self.width}x{self.height}")
        if not (0 <= cx < self.width and 0 <= cy < self.height):
            raise PerchError(
                f"principal point ({cx:.1f}, {cy:.1f}) lies outside a {self.width}x{self.height} image: "
                "the intrinsics do not belong to this image size"
            )
        object.__setattr__(self, "K", K)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def project(self, points_c: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) to pixel coordinates (..., 2)."""
        p = np.asarray(points_c, dtype=np.float64)
        z = p[..., 2]
        return np.stack([self.fx * p[..., 0] / z + self.cx, self.fy * p[..., 1] / z + self.cy], axis=-1)

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by `factor` (pixel centres stay consistent)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return Camera(K, round(self.width * factor), round(self.height * factor))


def entry_size(entry: dict, key: str, source: str) -> int | None:
    """The entry's optional `width`/`height`: a positive integer, or PerchError naming the value."""
    if key not in entry:
        return None
    v = entry[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not float(v).is_integer() or v <= 0:
        raise PerchError(f"{source}: '{key}' must be a positive whole number of pixels, got {v!r}")
    return int(v)


# Real cameras have the principal point within a few percent of the image centre; an image resized
# by 2x (either way) after calibration puts it 25 % or more away. 15 % separates the two.
PRINCIPAL_POINT_TOLERANCE = 0.15


def camera_from_entry(entry: dict, width: int, height: int, source: str = "camera", image: str = "") -> Camera:
    """A `Camera` from a BOP-style entry; width/height come from the image and are checked against the
    entry's `width`/`height` and against cam_K's principal point (the one rule for every command)."""
    try:
        K = np.asarray(entry["cam_K"], dtype=np.float64).reshape(3, 3)
    except (ValueError, TypeError, KeyError):
        raise PerchError(f"{source}: 'cam_K' must be 9 numbers, got {entry.get('cam_K')!r}") from None
    what = f"image {image}" if image else "the image"
    for key, actual in (("width", width), ("height", height)):
        said = entry_size(entry, key, source)
        if said is not None and said != actual:
            raise PerchError(f"{source}: {what} has {key} {actual} but the camera says {said}")
    try:
        cam = Camera(K, width, height)
    except PerchError as e:
        raise PerchError(f"{source}: {e}") from None
    tol = PRINCIPAL_POINT_TOLERANCE
    if abs(cam.cx - (width - 1) / 2) > tol * width or abs(cam.cy - (height - 1) / 2) > tol * height:
        raise PerchError(
            f"{what} is {width}x{height} but cam_K in {source} has its principal point at "
            f"({cam.cx:.1f}, {cam.cy:.1f}), implying about {round(2 * cam.cx + 1)}x{round(2 * cam.cy + 1)}: "
            "use the intrinsics of this image size"
        )
    return cam
