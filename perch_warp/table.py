"""The table frame and poses on it.

Table frame ("world" in BOP's `cam_R_w2c`/`cam_t_w2c`): +z is the table normal
pointing towards the camera side, z = 0 is the table top. All lengths here are
metres; BOP files carry millimetres and are converted at the boundary
(`Table.from_bop`).

A candidate pose is (x, y, yaw): the model origin at table point (x, y, z_m), the
model rotated by `Rz(yaw) @ R_rest`, where `RestingPose` holds how the object rests
(R_rest, z_m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import PerchError


def rot_z(yaw: np.ndarray | float) -> np.ndarray:
    """Rotation(s) about +z by `yaw` radians, shape (..., 3, 3)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(yaw), np.ones_like(yaw)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _check_rotation(R: np.ndarray, name: str) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(R)) or np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise PerchError(f"{name} is not a rotation matrix: {R.round(4).tolist()}")
    # Re-orthonormalise so that small rounding in JSON files does not skew renderings.
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def _check_extent(extent) -> np.ndarray:
    """A table extent as a (P, 2) float array of at least 3 finite corners enclosing some area (metres)."""
    e = np.asarray(extent, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] != 2 or len(e) < 3 or not np.all(np.isfinite(e)):
        raise PerchError(f"the table extent must be 3 or more finite [x, y] corners, got {np.asarray(extent).tolist()}")
    area = 0.5 * abs(float(np.dot(e[:, 0], np.roll(e[:, 1], -1)) - np.dot(e[:, 1], np.roll(e[:, 0], -1))))
    if area <= 0:
        raise PerchError(f"the table extent encloses no area: {e.tolist()}")
    return e


@dataclass(frozen=True)
class Table:
    """Rigid transform table -> camera: X_cam = R_t2c @ X_table + t_t2c_m (metres); and, where known, the
    table top's extent: the polygon (P, 2) of the table frame (metres) where an object can rest (None: the
    whole plane). A candidate whose model origin lies outside it is never scored (issue 17 (i): no
    object on a wall, a monitor or the floor beyond the table's edge)."""

    R_t2c: np.ndarray
    t_t2c_m: np.ndarray
    extent_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.extent_m is not None:
            object.__setattr__(self, "extent_m", _check_extent(self.extent_m))
        R = _check_rotation(self.R_t2c, "table rotation (cam_R_w2c)")
        t = np.asarray(self.t_t2c_m, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(t)):
            raise PerchError(f"table translation (cam_t_w2c) must be finite, got {t.tolist()}")
        object.__setattr__(self, "R_t2c", R)
        object.__setattr__(self, "t_t2c_m", t)
        if self.camera_center_table_m[2] <= 0:
            raise PerchError(
                "the table plane is behind the camera (camera centre is below the table top, "
                f"z = {self.camera_center_table_m[2]:.3f} m): check cam_R_w2c/cam_t_w2c"
            )

    @classmethod
    def from_bop(cls, cam_R_w2c, cam_t_w2c_mm, extent_mm=None) -> Table:
        """From BOP's `cam_R_w2c` (9 values) and `cam_t_w2c` (3 values, millimetres), and the optional
        table extent (a list of [x, y] corners in the table frame, millimetres: `table_extent_mm`)."""
        try:
            R = np.asarray(cam_R_w2c, dtype=np.float64).reshape(3, 3)
            t = np.asarray(cam_t_w2c_mm, dtype=np.float64).reshape(3) / 1000.0
        except (ValueError, TypeError):
            raise PerchError("cam_R_w2c must be 9 numbers and cam_t_w2c 3 numbers (mm)") from None
        if extent_mm is None:
            return cls(R, t)
        try:
            extent = np.asarray(extent_mm, dtype=np.float64) / 1000.0
        except (ValueError, TypeError):
            raise PerchError("table_extent_mm must be a list of [x, y] corners (mm, table frame)") from None
        return cls(R, t, extent)

    @classmethod
    def from_entry(cls, entry: dict, source: str = "camera") -> Table:
        """From a BOP `scene_camera.json` entry; fails clearly when it has no table."""
        if "cam_R_w2c" not in entry or "cam_t_w2c" not in entry:
            raise PerchError(
                f"{source}: no table frame (needs 'cam_R_w2c' and 'cam_t_w2c' in mm, world z = table normal); "
                "add them to the camera file (or, for a BOP dataset with depth images, use eval, which fits the table)"
            )
        try:
            return cls.from_bop(entry["cam_R_w2c"], entry["cam_t_w2c"], entry.get("table_extent_mm"))
        except PerchError as e:
            raise PerchError(f"{source}: {e}") from None

    def with_extent(self, extent_m) -> Table:
        """The same table with this extent (polygon (P, 2), table frame, metres)."""
        return Table(self.R_t2c, self.t_t2c_m, extent_m)

    def contains(self, x_m, y_m) -> np.ndarray:
        """Whether table points (x_m, y_m arrays, metres) lie on the table top's extent (all where it has none;
        points on an edge may go either way)."""
        x, y = np.broadcast_arrays(np.asarray(x_m, dtype=np.float64), np.asarray(y_m, dtype=np.float64))
        if self.extent_m is None:
            return np.ones(x.shape, dtype=bool)
        inside = np.zeros(x.shape, dtype=bool)
        poly = self.extent_m
        for (xa, ya), (xb, yb) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            crosses = (ya > y) != (yb > y)  # the edge spans the point's height: a ray to +x may cross it
            with np.errstate(divide="ignore", invalid="ignore"):
                x_cross = xa + (y - ya) * (xb - xa) / (yb - ya)
            inside ^= crosses & (x < x_cross)
        return inside

    @property
    def camera_center_table_m(self) -> np.ndarray:
        return -self.R_t2c.T @ self.t_t2c_m

    def to_camera(self, points_t_m: np.ndarray) -> np.ndarray:
        """Table-frame points (..., 3) to camera frame (metres)."""
        return np.asarray(points_t_m) @ self.R_t2c.T + self.t_t2c_m

    def ray_to_table(self, camera, uv: np.ndarray) -> np.ndarray:
        """Intersect pixel rays with the plane z = 0; returns table points (..., 3), NaN where the ray misses."""
        uv = np.asarray(uv, dtype=np.float64)
        d_c = np.stack(
            [(uv[..., 0] - camera.cx) / camera.fx, (uv[..., 1] - camera.cy) / camera.fy, np.ones(uv.shape[:-1])], -1
        )
        d_t = d_c @ self.R_t2c  # R^T d for row vectors
        c_t = self.camera_center_table_m
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -c_t[2] / d_t[..., 2]
        p = c_t + s[..., None] * d_t
        p[~(s > 0)] = np.nan
        return p


@dataclass(frozen=True)
class RestingPose:
    """How the object rests on the table at yaw 0: model -> table rotation and the model origin's height (m)."""

    R_rest: np.ndarray
    z_m: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "R_rest", _check_rotation(self.R_rest, "resting rotation"))
        if not np.isfinite(self.z_m):
            raise PerchError(f"resting height must be finite, got {self.z_m}")
        object.__setattr__(self, "z_m", float(self.z_m))

    @classmethod
    def upright(cls, vertices_m: np.ndarray, R_rest: np.ndarray | None = None, lift_m: float = 0.0) -> RestingPose:
        """Model +z along the table normal (or `R_rest`), the lowest vertex on the table top (plus `lift_m`)."""
        R = np.eye(3) if R_rest is None else np.asarray(R_rest, dtype=np.float64)
        z = -float((np.asarray(vertices_m) @ R.T)[:, 2].min()) + lift_m
        return cls(R, z)

    def model_to_table(self, x_m, y_m, yaw_rad) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (N, 3, 3) and translations (N, 3) in metres for candidate arrays x, y, yaw."""
        x_m, y_m, yaw_rad = np.broadcast_arrays(
            *(np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (x_m, y_m, yaw_rad))
        )
        R = rot_z(yaw_rad) @ self.R_rest
        t = np.stack([x_m, y_m, np.full_like(x_m, self.z_m)], -1)
        return R, t


def model_to_camera(table: Table, resting: RestingPose, x_m, y_m, yaw_rad) -> tuple[np.ndarray, np.ndarray]:
    """Model -> camera rotations (N, 3, 3) and translations (N, 3, metres) of candidates."""
    R_m2t, t_m2t = resting.model_to_table(x_m, y_m, yaw_rad)
    return table.R_t2c @ R_m2t, t_m2t @ table.R_t2c.T + table.t_t2c_m


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def decompose_on_table(table: Table, R_m2c: np.ndarray, t_m2c_m: np.ndarray) -> tuple[RestingPose, float, float, float]:
    """Split a model -> camera pose into (RestingPose, x_m, y_m, yaw_rad) on this table.

    yaw is the twist of the model -> table rotation about the table normal
    (swing-twist decomposition), so an upright object gets R_rest = I. This is how
    the evaluation takes height, roll and pitch from the ground truth (thesis §4.1).
    """
    R_m2c = np.asarray(R_m2c, dtype=np.float64).reshape(3, 3)
    R_m2t = table.R_t2c.T @ R_m2c
    t_m2t = table.R_t2c.T @ (np.asarray(t_m2c_m, dtype=np.float64).reshape(3) - table.t_t2c_m)
    # Quaternion w and z components of R_m2t give its twist about z.
    w = 0.5 * np.sqrt(max(0.0, 1.0 + np.trace(R_m2t)))
    qz = (R_m2t[1, 0] - R_m2t[0, 1]) / (4 * w) if w > 1e-6 else 0.0
    yaw = 2.0 * np.arctan2(qz, w) if (w > 1e-6 or abs(qz) > 1e-6) else 0.0
    yaw = float((yaw + np.pi) % (2 * np.pi) - np.pi)
    R_rest = rot_z(-yaw) @ R_m2t
    return RestingPose(R_rest, float(t_m2t[2])), float(t_m2t[0]), float(t_m2t[1]), yaw
