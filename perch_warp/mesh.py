"""Object meshes: what users have (textured OBJ, PLY with vertex colours, PLY/GLB with UVs), in metres."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import PerchError

# A tabletop object larger than this many "units" across can only be in millimetres.
_MM_DETECT_EXTENT = 5.0
# Largest extent, in metres after the unit, that a tabletop object can have: outside it the mesh is
# degenerate or its unit is wrong, which would otherwise surface later as an empty or off-image grid.
OBJECT_EXTENT_M = (0.002, 2.0)
# --untextured: a mesh with no material at all is searched in this uniform grey (silhouette and shading only).
UNTEXTURED_GREY = 0.5


def _obj_materials(path: Path) -> None:
    """An OBJ's material files (mtllib) and their diffuse textures (map_Kd) must exist: trimesh would
    otherwise search the object in a placeholder colour without a word."""
    mtllibs, uses_material = [], False
    with open(path, errors="replace") as f:
        for line in f:
            if line.startswith("mtllib"):
                mtllibs += line.split()[1:]
            elif line.startswith("usemtl"):
                uses_material = True
    if uses_material and not mtllibs:
        raise PerchError(f"mesh {path} uses a material (usemtl) but names no material file (mtllib)")
    for name in mtllibs:
        mtl = path.parent / name
        if not mtl.is_file():
            raise PerchError(f"mesh {path}: its material file {mtl} (mtllib) is missing: put it beside the mesh")
        with open(mtl, errors="replace") as f:
            for line in f:
                words = line.split()
                if words and words[0] == "map_Kd" and len(words) > 1:
                    tex = mtl.parent / words[-1]  # options such as -s u v come before the file name
                    if not tex.is_file():
                        raise PerchError(f"mesh {path}: texture {tex} (map_Kd in {mtl.name}) is missing")


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
        import trimesh  # not at the top: every command imports this module, trimesh takes ~0.5 s

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


def load_mesh(path: str | Path, units: str = "auto", untextured: bool = False) -> ObjectMesh:
    """Load a mesh file into metres.

    units: "mm", "m", or "auto" (millimetres when the largest extent exceeds 5 units,
    as BOP models do; the choice is recorded in `units_note` and reported by the CLI).
    untextured: search a mesh that has no material and no vertex colours at all in a uniform
    grey (never a mesh whose material or texture file is missing: that is an error).
    """
    path = Path(path)
    if not path.is_file():
        raise PerchError(f"mesh file not found: {path}")
    if units not in ("auto", "mm", "m"):
        raise PerchError(f"mesh units must be auto, mm or m, got {units!r}")
    loaded = _read_trimesh(path)
    V = np.asarray(loaded.vertices, dtype=np.float64)
    F = np.asarray(loaded.faces, dtype=np.int32)
    if not np.all(np.isfinite(V)):
        raise PerchError(f"mesh {path} has non-finite vertex coordinates")
    scale, note = _unit_scale(path, V, units)
    uv, texture, colors = _appearance(loaded.visual, path, len(V), untextured)
    if texture is None and colors is None:
        colors = np.full((len(V), 3), UNTEXTURED_GREY, np.float32)
        note += ", untextured: uniform grey"
    return ObjectMesh(V * scale, F, uv, texture, colors, str(path), note)


def _read_trimesh(path: Path):
    """The file as one trimesh.Trimesh with at least one face, unprocessed (an OBJ's materials checked first)."""
    import trimesh  # see hull_points_m

    if path.suffix.lower() == ".obj":
        _obj_materials(path)
    try:
        loaded = trimesh.load(str(path), process=False, force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise PerchError(f"cannot read mesh {path}: {e}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise PerchError(f"mesh {path} has no faces")
    return loaded


def _unit_scale(path: Path, V: np.ndarray, units: str) -> tuple[float, str]:
    """Metres per unit of vertices V (units "auto", "mm" or "m") and the note saying how it was chosen;
    refuses a degenerate mesh and one whose size in metres is not a tabletop object's (OBJECT_EXTENT_M)."""
    extents = V.max(0) - V.min(0)
    extent = float(extents.max())
    if units == "auto":
        scale = 1e-3 if extent > _MM_DETECT_EXTENT else 1.0
        note = f"{'mm' if scale == 1e-3 else 'm'} (auto: largest extent {extent:g} units)"
    else:
        scale = 1e-3 if units == "mm" else 1.0
        note = f"{units} (given)"
    unit = "mm" if scale == 1e-3 else "m"
    size = " x ".join(f"{e:g}" for e in extents)
    lo, hi = OBJECT_EXTENT_M
    if np.count_nonzero(extents > 0) < 2:
        raise PerchError(f"mesh {path} is degenerate: its extent is {size} units (a point or a line)")
    if not lo <= extent * scale <= hi:
        other, other_scale = ("m", 1.0) if unit == "mm" else ("mm", 1e-3)
        fix = (
            f"if its unit is {other}, pass --mesh-units {other}"
            if lo <= extent * other_scale <= hi
            else "check the mesh file"
        )
        raise PerchError(
            f"mesh {path} is {size} units across, read as {unit} ({'auto' if units == 'auto' else 'given'}): "
            f"{extent * scale:g} m, outside the {lo * 1000:g} mm .. {hi:g} m of a tabletop object; {fix}"
        )
    return scale, note


def _appearance(visual, path: Path, n_vertices: int, untextured: bool):
    """(uv, texture, colors) of a trimesh visual, None where absent: a texture image with its UVs, a
    material's plain diffuse colour or vertex colours as per vertex colours. Neither texture nor
    colours is refused unless `untextured` and the mesh has no material at all."""
    uv = texture = colors = None
    if getattr(visual, "kind", None) == "texture" and getattr(visual, "uv", None) is not None:
        texture = _texture_image(visual, path)
        if texture is not None:
            uv = np.asarray(visual.uv, dtype=np.float32)[:, :2]
            if len(uv) != n_vertices:
                raise PerchError(f"mesh {path}: {len(uv)} UVs for {n_vertices} vertices")
        else:
            # A material with a plain diffuse colour but no image: use it as a uniform colour.
            mat = getattr(visual, "material", None)
            diffuse = getattr(mat, "diffuse", None) if mat is not None else None
            if diffuse is not None:
                colors = np.tile(np.asarray(diffuse, dtype=np.float32)[:3] / 255.0, (n_vertices, 1))
    elif getattr(visual, "kind", None) == "vertex":
        colors = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    if texture is None and colors is None:
        has_material = getattr(visual, "kind", None) == "texture" and getattr(visual, "material", None) is not None
        if not untextured or has_material:
            raise PerchError(
                f"mesh {path} has no texture and no vertex colours: the search needs its appearance "
                "(--untextured searches a mesh without any material in uniform grey)"
            )
    return uv, texture, colors
