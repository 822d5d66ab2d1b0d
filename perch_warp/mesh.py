"""Object meshes: what users have (textured OBJ, PLY with vertex colours, PLY/GLB with UVs), in metres."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import PerchError

# A tabletop object larger than this many "units" across can only be in millimetres.
_MM_DETECT_EXTENT = 5.0


@dataclass(frozen=True)
class ObjectMesh:
    """A triangle mesh in its model frame, lengths in metres, with its appearance.

    Exactly one of (`uv`, `texture`) or `vertex_colors` describes the appearance.
    `texture` is float32 (H, W, 3) in [0, 1] with row 0 at texture v = 0 (OBJ images
    are stored top row first, so they are flipped once here).
    """

    vertices_m: np.ndarray  # (N, 3) float64, model frame, metres
    faces: np.ndarray  # (F, 3) int32
    uv: np.ndarray | None = None  # (N, 2) float32
    texture: np.ndarray | None = None  # (H, W, 3) float32
    vertex_colors: np.ndarray | None = None  # (N, 3) float32 in [0, 1]
    source: str = ""
    units_note: str = ""

    @property
    def extent_m(self) -> np.ndarray:
        return self.vertices_m.max(0) - self.vertices_m.min(0)

    def hull_points_m(self) -> np.ndarray:
        """Convex-hull vertices (model frame, m): enough to bound every projection of the mesh."""
        import trimesh

        try:
            return np.asarray(trimesh.convex.convex_hull(self.vertices_m).vertices, dtype=np.float64)
        except Exception:  # flat or degenerate meshes have no 3-D hull; all vertices still bound it
            return self.vertices_m


def _texture_image(visual, path: Path) -> np.ndarray | None:
    mat = getattr(visual, "material", None)
    if mat is None:
        return None
    if path.suffix.lower() == ".ply" and b"TextureFile" not in path.read_bytes()[:65536]:
        # trimesh puts a 2x2 placeholder image on PLY UVs without a texture file.
        raise PerchError(
            f"mesh {path} has UVs but no texture image: name it in a 'comment TextureFile NAME.png' header line"
        )
    img = getattr(mat, "image", None)
    factor = np.ones(3, np.float32)
    if img is None:
        img = getattr(mat, "baseColorTexture", None)
        bcf = getattr(mat, "baseColorFactor", None)
        if bcf is not None:  # glTF: the factor multiplies the texture
            factor = np.asarray(bcf, np.float32)[:3] / (255.0 if np.asarray(bcf).dtype.kind in "ui" else 1.0)
    if img is None:
        return None
    arr = np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0 * factor
    return np.ascontiguousarray(arr[::-1])


def load_mesh(path: str | Path, units: str = "auto") -> ObjectMesh:
    """Load a mesh file into metres.

    units: "mm", "m", or "auto" (millimetres when the largest extent exceeds 5 units,
    as BOP models do; the choice is recorded in `units_note` and reported by the CLI).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise PerchError(f"mesh file not found: {path}")
    if units not in ("auto", "mm", "m"):
        raise PerchError(f"mesh units must be auto, mm or m, got {units!r}")
    try:
        loaded = trimesh.load(str(path), process=False, force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise PerchError(f"cannot read mesh {path}: {e}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise PerchError(f"mesh {path} has no faces")
    V = np.asarray(loaded.vertices, dtype=np.float64)
    F = np.asarray(loaded.faces, dtype=np.int32)
    if not np.all(np.isfinite(V)):
        raise PerchError(f"mesh {path} has non-finite vertex coordinates")

    extent = float((V.max(0) - V.min(0)).max())
    if extent <= 0:
        raise PerchError(f"mesh {path} is degenerate (zero extent)")
    if units == "auto":
        scale = 1e-3 if extent > _MM_DETECT_EXTENT else 1.0
        note = f"{'mm' if scale == 1e-3 else 'm'} (auto: largest extent {extent:g} units)"
    else:
        scale = 1e-3 if units == "mm" else 1.0
        note = f"{units} (given)"

    uv = texture = colors = None
    visual = loaded.visual
    if getattr(visual, "kind", None) == "texture" and getattr(visual, "uv", None) is not None:
        texture = _texture_image(visual, path)
        if texture is not None:
            uv = np.asarray(visual.uv, dtype=np.float32)[:, :2]
            if len(uv) != len(V):
                raise PerchError(f"mesh {path}: {len(uv)} UVs for {len(V)} vertices")
        else:
            # A material with a plain diffuse colour but no image: use it as a uniform colour.
            mat = getattr(visual, "material", None)
            diffuse = getattr(mat, "diffuse", None) if mat is not None else None
            if diffuse is not None:
                colors = np.tile(np.asarray(diffuse, dtype=np.float32)[:3] / 255.0, (len(V), 1))
    elif getattr(visual, "kind", None) == "vertex":
        colors = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    if texture is None and colors is None:
        raise PerchError(f"mesh {path} has no texture and no vertex colours: the search needs its appearance")
    return ObjectMesh(V * scale, F, uv, texture, colors, str(path), note)
