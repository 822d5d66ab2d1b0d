"""The meshes a synthetic set places: their vertices, footprint and texture (BOP models, millimetres)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from ..errors import PerchError


@dataclass(frozen=True)
class ModelSpec:
    """What the generator needs of one mesh; lengths in millimetres (BOP model units)."""

    obj_id: int
    obj_path: str
    texture_path: str | None
    min_z: float
    hull_xy: np.ndarray  # (K, 2) convex footprint, counter-clockwise
    bbox_corners: np.ndarray  # (8, 3)
    vertices: np.ndarray = field(repr=False)  # (N, 3), kept for the in-view check


def read_obj_vertices(path: Path) -> np.ndarray:
    """The ``v`` lines of a Wavefront OBJ as an (N, 3) float array."""
    rows = []
    try:
        with open(path) as f:
            for line in f:
                if line.startswith("v "):
                    rows.append(line.split()[1:4])
    except OSError as e:
        raise PerchError(f"cannot read model {path}: {e}") from None
    try:
        v = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise PerchError(f"model {path} has malformed vertex lines") from None
    if len(v) < 4 or not np.all(np.isfinite(v)):
        raise PerchError(f"model {path} has fewer than 4 finite vertices")
    return v


def _texture_of(obj_path: Path) -> str | None:
    """The diffuse texture named by the OBJ's material file, else ``<stem>.png`` beside it."""
    mtl = obj_path.with_suffix(".mtl")
    if mtl.is_file():
        for line in mtl.read_text(errors="replace").splitlines():
            parts = line.split()
            if len(parts) >= 2 and parts[0] == "map_Kd":
                tex = obj_path.parent / parts[-1]
                if tex.is_file():
                    return str(tex.resolve())
                raise PerchError(f"{mtl} names texture {parts[-1]}, which does not exist")
    png = obj_path.with_suffix(".png")
    return str(png.resolve()) if png.is_file() else None


def _convex_hull_ccw(points: np.ndarray) -> np.ndarray:
    hull = ConvexHull(points)
    return points[hull.vertices]  # scipy gives 2-D hull vertices counter-clockwise


def load_model(models_dir: Path, obj_id: int) -> ModelSpec:
    path = models_dir / f"obj_{obj_id:06d}.obj"
    if not path.is_file():
        raise PerchError(f"model for object id {obj_id} not found: {path}")
    v = read_obj_vertices(path)
    lo, hi = v.min(0), v.max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return ModelSpec(
        obj_id=obj_id,
        obj_path=str(path.resolve()),
        texture_path=_texture_of(path),
        min_z=float(lo[2]),
        hull_xy=_convex_hull_ccw(v[:, :2]),
        bbox_corners=corners,
        vertices=v,
    )


def available_ids(models_dir: Path) -> list[int]:
    ids = []
    for p in models_dir.glob("obj_*.obj"):
        try:
            ids.append(int(p.stem[4:]))
        except ValueError:
            continue
    return sorted(ids)
