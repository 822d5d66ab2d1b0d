"""Pinhole camera intrinsics (OpenCV/BOP convention: pixel (u, v) centres are integers)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

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


def read_camera_json(path: str | Path, image_id: int | None = None) -> dict:
    """One camera entry from a BOP `scene_camera.json` (or a flat dict with `cam_K`).

    BOP files map image ids to entries; `image_id` picks one, and may be omitted when
    the file holds exactly one entry.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise PerchError(f"camera file not found: {path}") from None
    except (OSError, ValueError) as e:
        raise PerchError(f"cannot read camera file {path}: {e}") from None
    if not isinstance(data, dict):
        raise PerchError(f"camera file {path} must hold a JSON object")
    if "cam_K" in data:
        return data
    if image_id is not None:
        entry = data.get(str(image_id))
        if entry is None:
            raise PerchError(f"camera file {path} has no entry for image id {image_id} (has {sorted(data)[:10]})")
    elif len(data) == 1:
        entry = next(iter(data.values()))
    else:
        raise PerchError(f"camera file {path} has {len(data)} entries; say which with --image-id")
    if not isinstance(entry, dict) or "cam_K" not in entry:
        raise PerchError(f"camera entry in {path} has no 'cam_K'")
    return entry


def camera_from_entry(entry: dict, width: int, height: int, source: str = "camera") -> Camera:
    """A `Camera` from a BOP-style entry; width/height come from the image (checked against the entry's)."""
    try:
        K = np.asarray(entry["cam_K"], dtype=np.float64).reshape(3, 3)
    except (ValueError, TypeError):
        raise PerchError(f"{source}: 'cam_K' must be 9 numbers, got {entry.get('cam_K')!r}") from None
    for key, actual in (("width", width), ("height", height)):
        if key in entry and int(entry[key]) != actual:
            raise PerchError(f"{source}: image {key} is {actual} but the camera says {entry[key]}")
    try:
        return Camera(K, width, height)
    except PerchError as e:
        raise PerchError(f"{source}: {e}") from None
