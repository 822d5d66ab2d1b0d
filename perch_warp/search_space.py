"""The search space: a grid of (x, y, yaw) on the table plane (metres, radians)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .errors import PerchError
from .table import Table

FULL_CIRCLE = (0.0, 2 * math.pi)


def _axis(lo: float, hi: float, step: float, name: str, unit: str) -> np.ndarray:
    if not all(math.isfinite(v) for v in (lo, hi, step)):
        raise PerchError(f"{name} range and step must be finite, got {lo}..{hi} step {step}")
    if step <= 0:
        raise PerchError(f"{name} step must be positive, got {step} {unit}")
    if hi < lo:
        raise PerchError(f"{name} range is empty: {lo} > {hi} {unit}")
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    return lo + step * np.arange(n)


@dataclass(frozen=True)
class SearchSpace:
    """x, y (table frame, metres; inclusive ranges) and yaw (radians about the table normal).

    A yaw range spanning the full circle excludes its end point (it equals the start).
    """

    x_range_m: tuple[float, float]
    y_range_m: tuple[float, float]
    xy_step_m: float = 0.01
    yaw_range_rad: tuple[float, float] = FULL_CIRCLE
    yaw_step_rad: float = math.radians(5.0)

    @property
    def full_circle(self) -> bool:
        """Whether the yaw range spans the whole circle (yaw then wraps: its end is its start)."""
        return self.yaw_range_rad[1] - self.yaw_range_rad[0] >= 2 * math.pi - 1e-9

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        xs = _axis(*self.x_range_m, self.xy_step_m, "x", "m")
        ys = _axis(*self.y_range_m, self.xy_step_m, "y", "m")
        ylo, yhi = self.yaw_range_rad
        yaws = _axis(ylo, yhi, self.yaw_step_rad, "yaw", "rad")
        if self.full_circle:
            yaws = yaws[yaws < ylo + 2 * math.pi - 1e-9]
        return xs, ys, yaws

    def __len__(self) -> int:
        return math.prod(len(a) for a in self.axes())

    def candidates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat (x_m, y_m, yaw_rad) arrays, yaw varying fastest (neighbours render alike)."""
        xs, ys, yaws = self.axes()
        X, Y, A = np.meshgrid(xs, ys, yaws, indexing="ij")
        return X.ravel(), Y.ravel(), A.ravel()

    def at(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Table-frame (x_m, y_m, yaw_rad) of the candidates with these flat indices into candidates()'s order
        ((i_x * n_y + i_y) * n_yaw + i_yaw), without setting up the others."""
        xs, ys, yaws = self.axes()
        i, rest = np.divmod(np.asarray(flat, dtype=np.int64), len(ys) * len(yaws))
        j, k = np.divmod(rest, len(yaws))
        return xs[i], ys[j], yaws[k]

    def sample(self, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Table-frame (x_m, y_m, yaw_rad) of min(n, len(self)) distinct candidates drawn at random (`seed`),
        without setting up the others."""
        size = len(self)
        return self.at(np.random.default_rng(seed).choice(size, min(n, size), replace=False))

    def describe(self) -> str:
        xs, ys, yaws = self.axes()
        (x0, x1), (y0, y1) = self.x_range_m, self.y_range_m
        a0, a1 = (math.degrees(a) for a in self.yaw_range_rad)
        return (
            f"x {x0:+.3f}..{x1:+.3f} m, y {y0:+.3f}..{y1:+.3f} m step {self.xy_step_m * 100:g} cm, "
            f"yaw {a0:g}..{a1:g} deg step {math.degrees(self.yaw_step_rad):g} deg: "
            f"{len(xs)} x {len(ys)} x {len(yaws)} = {len(xs) * len(ys) * len(yaws)} candidates"
        )

    @classmethod
    def visible_table(
        cls,
        camera: Camera,
        table: Table,
        xy_step_m: float = 0.01,
        yaw_step_rad: float = math.radians(5.0),
        clip_m: float = 1.0,
        margin_px: float = 0.0,
    ) -> SearchSpace:
        """The part of the table top the image sees, clipped to a clip_m x clip_m square.

        The square is centred where the principal ray meets the table (the middle of
        the view), never on anything derived from a ground truth.
        """
        us = np.linspace(margin_px, camera.width - 1 - margin_px, 33)
        vs = np.linspace(margin_px, camera.height - 1 - margin_px, 25)
        uv = np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2)
        pts = table.ray_to_table(camera, uv)
        pts = pts[np.isfinite(pts[:, 0])]
        if len(pts) == 0:
            raise PerchError("the camera does not see the table plane (no image ray meets it)")
        centre = table.ray_to_table(camera, np.array([camera.cx, camera.cy]))
        if not np.all(np.isfinite(centre)):
            centre = np.median(pts, axis=0)
        half = clip_m / 2
        lo = np.maximum(pts[:, :2].min(0), centre[:2] - half)
        hi = np.minimum(pts[:, :2].max(0), centre[:2] + half)
        # Snap to the step so grids of nearby views share cells.
        lo = np.floor(lo / xy_step_m) * xy_step_m
        hi = np.ceil(hi / xy_step_m) * xy_step_m
        return cls((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])), xy_step_m, FULL_CIRCLE, yaw_step_rad)
