"""Rendering candidates: project their boxes, pack them, and ray-cast with kernel #1.

No lighting, as in the thesis: a pixel's colour is the texture (or vertex colour)
at the first surface its ray meets; the score term shade=s (perch_warp.score_terms) lights it from
one direction (kernels/render.py: Shading). Two ways to find that surface, with the same rays and
the same ray-triangle test: "bvh" queries Warp's mesh BVH per ray (kernels/render.py),
"raster" lets each triangle test the rays its projection covers (kernels/raster.py),
which is faster on a CPU (docs/performance.md, "Raster form of kernel #1").

Each form is a `Renderer` class (BvhRenderer, RasterRenderer) with `render()` (kernel #1 for a
batch) and `silhouette()` (the feature points its mask covers, for the bound); both share one
`DeviceMesh` (vertices, faces and the MeshLook appearance struct, uploaded once per mesh).
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import trimesh
import warp as wp

from .camera import Camera
from .errors import PerchError
from .kernels import bound as bound_kernels
from .kernels import boxes as box_kernels
from .kernels import raster as raster_kernels
from .kernels.features import PointLayout
from .kernels.render import MeshLook, PixelRays, RenderedBoxes, Shading, render_boxes
from .mesh import ObjectMesh
from .mipmap import set_mip
from .score_terms import TEXTURES

# Candidates closer than this to the camera plane cannot be rendered sensibly.
MIN_DEPTH_M = 0.02
# "auto": on the CPU raster or bvh by RASTER_FACES_PER_PIXEL, on a GPU bvh (the raster form is not measured there).
RENDERERS = ("auto", "bvh", "raster")
# The raster form's cost grows with faces x candidates, the BVH form's with rays (pixels). On the CPU
# its render alone was measured faster up to about 20 faces per pixel of a candidate's box, but its
# exact silhouette bound visits every face for every candidate: whole pruned searches were measured
# 2x faster at 1.5 faces per pixel and about even near 6.5 (docs/performance.md, "Raster form of
# kernel #1"), so auto picks it only where it clearly wins.
RASTER_FACES_PER_PIXEL = 3
# The raster form projects every vertex for every candidate: at most this many (candidate, vertex)
# pairs at once (12 bytes each), so memory stays bounded whatever the batch.
VERTEX_SLOTS = 1 << 22


def auto_renderer(device: str, n_faces: int, median_box_px: float) -> str:
    """What --renderer auto runs: bvh on a GPU; on the CPU raster unless the mesh has more than
    RASTER_FACES_PER_PIXEL faces per pixel of the median candidate box."""
    if not wp.get_device(device).is_cpu:
        return "bvh"
    return "raster" if n_faces <= RASTER_FACES_PER_PIXEL * median_box_px else "bvh"


def is_closed_surface(vertices_m: np.ndarray, faces: np.ndarray) -> bool:
    """True when the faces, with vertices at bit-identical float32 positions merged (texture seams
    split vertices, not the surface), close a volume with outward winding: every edge shared by
    exactly two faces in opposite directions, positive signed volume. Then, seen from outside,
    the nearest hit of any ray lies on a face turned towards it, and back faces can be skipped."""
    v = np.asarray(vertices_m, dtype=np.float32)
    uniq, inverse = np.unique(v, axis=0, return_inverse=True)
    tm = trimesh.Trimesh(uniq.astype(np.float64), inverse.reshape(-1)[np.asarray(faces)], process=False)
    return bool(tm.is_watertight and tm.is_winding_consistent and tm.volume > 0)


def project_boxes(camera: Camera, hull_m: np.ndarray, R_m2c: np.ndarray, t_m2c_m: np.ndarray) -> np.ndarray:
    """Pixel boxes (N, 4) = (x0, y0, w, h) covering each candidate's whole projection.

    Boxes are not clipped to the image: the part of a silhouette outside the picture
    still counts towards the object's size (see kernels/features.py). `hull_m` are
    model-frame points (m) whose projection bounds the mesh's (its convex hull).
    w = h = 0 where the candidate does not overlap the image; -1 where it is behind or
    too close to the camera.
    """
    out = np.zeros((len(R_m2c), 4), dtype=np.int32)
    chunk = max(1, 2_000_000 // max(1, len(hull_m)))
    for s in range(0, len(R_m2c), chunk):
        P = np.einsum("nij,kj->nki", R_m2c[s : s + chunk], hull_m) + t_m2c_m[s : s + chunk, None, :]
        z = P[..., 2]
        behind = z.min(1) < MIN_DEPTH_M
        z = np.where(z < MIN_DEPTH_M, MIN_DEPTH_M, z)
        u = camera.fx * P[..., 0] / z + camera.cx
        v = camera.fy * P[..., 1] / z + camera.cy
        x0, x1 = np.floor(u.min(1)), np.ceil(u.max(1))
        y0, y1 = np.floor(v.min(1)), np.ceil(v.max(1))
        w, h = x1 - x0 + 1, y1 - y0 + 1
        empty = (x1 < 0) | (y1 < 0) | (x0 > camera.width - 1) | (y0 > camera.height - 1)
        box = np.stack([x0, y0, w, h], -1)
        box[empty] = 0
        box[behind] = -1
        out[s : s + chunk] = box
    return out


class BoxProjector:
    """`project_boxes` on a Warp device (kernels/boxes.py, one thread per candidate), hull uploaded once.

    NumPy's version spends most of its time in the (candidates x hull points) einsum;
    here only the poses go up and one int4 per candidate comes back.
    """

    def __init__(self, hull_m: np.ndarray, device: str):
        self.device = device
        self.hull_m = np.asarray(hull_m, dtype=np.float64)
        self.hull = wp.array(self.hull_m, dtype=wp.vec3d, device=device)

    def __call__(self, camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray) -> np.ndarray:
        """Boxes (N, 4) int32, equal to project_boxes(camera, hull_m, R_m2c, t_m2c_m)."""
        n = len(R_m2c)
        if n == 0:
            return np.zeros((0, 4), dtype=np.int32)
        with wp.ScopedDevice(self.device):
            out = wp.empty(n, dtype=wp.vec4i)
            wp.launch(
                box_kernels.project_boxes,
                dim=n,
                inputs=[
                    self.hull,
                    wp.array(np.ascontiguousarray(R_m2c, dtype=np.float64), dtype=wp.mat33d),
                    wp.array(np.ascontiguousarray(t_m2c_m, dtype=np.float64), dtype=wp.vec3d),
                    camera.fx,
                    camera.fy,
                    camera.cx,
                    camera.cy,
                    camera.width,
                    camera.height,
                    MIN_DEPTH_M,
                ],
                outputs=[out],
            )
        return out.numpy().reshape(n, 4)


@dataclass
class RenderedBatch:
    """Kernel #1's output for a batch, still on the device."""

    rgb: wp.array  # (P,) vec3, RGB in [0, 1]
    mask: wp.array  # (P,) uint8
    box: wp.array  # (B,) vec4i image boxes
    pix_off: wp.array  # (B + 1,) int32 flat offsets
    n: int

    def as_struct(self) -> RenderedBoxes:
        """The batch as kernel #2 reads it (kernels/render.py: RenderedBoxes); the same device arrays."""
        seen = RenderedBoxes()
        seen.rgb, seen.mask, seen.box, seen.pix_off = self.rgb, self.mask, self.box, self.pix_off
        return seen


def flat_offsets(boxes: np.ndarray) -> np.ndarray:
    """Offsets (B + 1,) int32 of boxes (x0, y0, w, h) packed flat, w*h items each, row by row:
    the layout of the render, score and bound kernels (pixels or feature-grid cells)."""
    areas = boxes[:, 2].astype(np.int64) * boxes[:, 3]
    return np.concatenate([[0], np.cumsum(areas)]).astype(np.int32)


def camera_in_model(R_m2c: np.ndarray, t_m2c_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose, the camera-to-model rotation (N, 3, 3) float32 and the camera centre in the model
    frame (N, 3) float32 metres: rays are cast in the model frame, through one BVH for all poses."""
    R_c2m = np.ascontiguousarray(np.transpose(R_m2c, (0, 2, 1)), dtype=np.float32)
    origin_m = -np.einsum("nij,nj->ni", R_c2m.astype(np.float64), t_m2c_m).astype(np.float32)
    return R_c2m, origin_m


def pixel_rays(camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray, device: str) -> PixelRays:
    """The pixel rays of poses R_m2c (N, 3, 3), t_m2c_m (N, 3) metres (model to camera) through
    `camera`'s pixels, in the model frame, as the kernels take them (kernels/render.py: PixelRays)."""
    R_c2m, origin_m = camera_in_model(R_m2c, t_m2c_m)
    rays = PixelRays()
    rays.fx, rays.fy, rays.cx, rays.cy = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    rays.rot_c2m = wp.array(R_c2m, dtype=wp.mat33, device=device)
    rays.origin_m = wp.array(origin_m, dtype=wp.vec3, device=device)
    return rays


def point_layout(
    boxes: np.ndarray | wp.array, gboxes: np.ndarray, kernel_size: int, stride: int, device: str
) -> PointLayout:
    """Candidates' feature points as every kernel that walks them takes them (kernels/features.py:
    PointLayout): pixel boxes (B, 4) (a vec4i device array is used as it is, e.g. a RenderedBatch's)
    and their grid boxes (B, 4) (score.grid_boxes), built once per batch on the host and uploaded."""
    gboxes = np.asarray(gboxes, dtype=np.int32)
    pt_off = flat_offsets(gboxes)
    pts = PointLayout()
    with wp.ScopedDevice(device):
        pts.box = boxes if isinstance(boxes, wp.array) else wp.array(np.asarray(boxes, np.int32), dtype=wp.vec4i)
        pts.gbox = wp.array(gboxes, dtype=wp.vec4i)
        pts.pt_off = wp.array(pt_off, dtype=wp.int32)
    pts.n_cand = len(gboxes)
    pts.n_points = int(pt_off[-1])
    pts.ks = int(kernel_size)
    pts.stride = int(stride)
    return pts


class DeviceMesh:
    """A mesh and its appearance uploaded once to a Warp device (model frame, metres), shared by
    every renderer of that mesh. `texture`: "bilinear" (one lookup per pixel ray, the thesis's) or
    "mip" (mip-mapped lookups, perch_warp.mipmap; the score term texture=mip)."""

    def __init__(self, mesh: ObjectMesh, device: str, texture: str = "bilinear"):
        if texture not in TEXTURES:
            raise PerchError(f"texture lookup must be one of {', '.join(TEXTURES)}, got {texture!r}")
        self.device = device
        self.mesh = mesh
        with wp.ScopedDevice(device):
            self.points = wp.array(mesh.vertices_m.astype(np.float32), dtype=wp.vec3)
            self.indices = wp.array(mesh.faces.reshape(-1).astype(np.int32), dtype=wp.int32)
            look = MeshLook()
            look.indices = self.indices
            if mesh.texture is not None:
                look.use_texture = 1
                look.uvs = wp.array(mesh.uv.astype(np.float32), dtype=wp.vec2)
                look.texture = wp.array(mesh.texture.astype(np.float32), dtype=wp.vec3)
                look.colors = wp.zeros(1, dtype=wp.vec3)
            else:
                look.use_texture = 0
                look.uvs = wp.zeros(1, dtype=wp.vec2)
                look.texture = wp.zeros((1, 1), dtype=wp.vec3)
                look.colors = wp.array(mesh.vertex_colors.astype(np.float32), dtype=wp.vec3)
            set_mip(look, mesh if texture == "mip" else None)
            self.look = look

    @functools.cached_property
    def normals(self) -> wp.array:
        """Unit vertex normals (model frame) on the device, for shading (computed on first use): the
        angle-weighted mean of the faces' normals around each position, vertices at bit-identical
        float32 positions merged first, so a texture seam does not crease the shading."""
        v = np.asarray(self.mesh.vertices_m, dtype=np.float32)
        uniq, inverse = np.unique(v, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        tm = trimesh.Trimesh(uniq.astype(np.float64), inverse[np.asarray(self.mesh.faces)], process=False)
        return wp.array(np.asarray(tm.vertex_normals)[inverse].astype(np.float32), dtype=wp.vec3, device=self.device)

    @functools.cached_property
    def _no_normals(self) -> wp.array:
        """The unshaded render's placeholder (Shading.normals is not read when strength is 0)."""
        return wp.zeros(1, dtype=wp.vec3, device=self.device)

    def shading(self, light_m: np.ndarray | None = None, strength: float = 0.0) -> Shading:
        """Kernel #1's Shading: lit from the unit direction light_m (model frame, towards the light) with
        `strength` in [0, 1]; unshaded (the thesis's render) when strength is 0."""
        sh = Shading()
        sh.strength = float(strength)
        if sh.strength == 0.0:
            sh.normals = self._no_normals
            sh.light_m = wp.vec3(0.0, 0.0, 1.0)
        else:
            light = np.asarray(light_m, dtype=np.float64).reshape(3)
            sh.normals = self.normals
            sh.light_m = wp.vec3(*(light / np.linalg.norm(light)).astype(np.float32))
        return sh

    @functools.cached_property
    def closed_surface(self) -> bool:
        """The mesh closes a volume, outward (is_closed_surface); computed on first use."""
        return is_closed_surface(self.mesh.vertices_m, self.mesh.faces)


class Renderer(ABC):
    """One form of kernel #1 over a DeviceMesh. `render` colours candidates' boxes; `silhouette` says
    which feature points the same render's mask covers (what the pruned search's bound needs). Every
    form casts the same pixel rays (pixel_rays) with the same ray-triangle test: the same images."""

    name: ClassVar[str]

    def __init__(self, dmesh: DeviceMesh):
        self.dmesh = dmesh
        self.device = dmesh.device
        self.mesh = dmesh.mesh

    @property
    def cull_back_faces(self) -> bool:
        """Whether this form skips faces turned away from the camera (only where that cannot change a pixel)."""
        return False

    def pixel_rays(self, camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray) -> PixelRays:
        """The candidates' pixel rays on this device, for every kernel that casts them (model-to-camera
        poses R (B, 3, 3), t (B, 3) metres)."""
        return pixel_rays(camera, R_m2c, t_m2c_m, self.device)

    def render(
        self,
        camera: Camera,
        R_m2c: np.ndarray,
        t_m2c_m: np.ndarray,
        boxes: np.ndarray,
        shading: Shading | None = None,
    ) -> RenderedBatch:
        """Ray-cast each candidate's box (boxes (B, 4) pixels, w, h > 0; poses model to camera, metres):
        colour and mask per box pixel, device arrays in the layout of flat_offsets(boxes). `shading`
        (DeviceMesh.shading) lights the colours; none: unshaded, as in the thesis."""
        boxes = np.asarray(boxes, dtype=np.int32)
        pix_off = flat_offsets(boxes)
        n_pix = int(pix_off[-1])
        rays = self.pixel_rays(camera, R_m2c, t_m2c_m)
        with wp.ScopedDevice(self.device):
            batch = RenderedBatch(
                rgb=wp.empty(n_pix, dtype=wp.vec3),
                mask=wp.empty(n_pix, dtype=wp.uint8),
                box=wp.array(boxes, dtype=wp.vec4i),
                pix_off=wp.array(pix_off, dtype=wp.int32),
                n=len(boxes),
            )
            self._render(rays, batch, n_pix, shading or self.dmesh.shading())
        return batch

    @abstractmethod
    def _render(self, rays: PixelRays, batch: RenderedBatch, n_pix: int, shading: Shading) -> None:
        """Fill batch.rgb and batch.mask (n_pix pixels) from `rays`, lit by `shading`, on this device (scoped)."""

    @abstractmethod
    def silhouette(self, camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray, layout: PointLayout) -> wp.array:
        """uint8 per feature point of `layout`: 1 where the point's pixel ray hits the mesh inside its
        candidate's box, i.e. exactly where render()'s mask covers the point, else 0."""

    def render_image(
        self, camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray, shading: Shading | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The whole image for one pose: RGB float32 (H, W, 3) in [0, 1] and mask bool (H, W)."""
        box = np.array([[0, 0, camera.width, camera.height]], dtype=np.int32)
        b = self.render(camera, np.asarray(R_m2c)[None], np.asarray(t_m2c_m)[None], box, shading)
        rgb = b.rgb.numpy().reshape(camera.height, camera.width, 3)
        mask = b.mask.numpy().reshape(camera.height, camera.width).astype(bool)
        return rgb, mask


class BvhRenderer(Renderer):
    """Kernel #1 as one closest-hit query of Warp's mesh BVH per pixel ray (kernels/render.py); its
    silhouette casts any-hit rays through the same BVH (kernels/bound.py: anyhit_points)."""

    name = "bvh"

    def __init__(self, dmesh: DeviceMesh):
        super().__init__(dmesh)
        with wp.ScopedDevice(self.device):
            self.wp_mesh = wp.Mesh(points=dmesh.points, indices=dmesh.indices)

    def _render(self, rays: PixelRays, batch: RenderedBatch, n_pix: int, shading: Shading) -> None:
        wp.launch(
            render_boxes,
            dim=n_pix,
            inputs=[self.wp_mesh.id, self.dmesh.look, rays, batch.box, batch.pix_off, batch.n, shading],
            outputs=[batch.rgb, batch.mask],
        )

    def silhouette(self, camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray, layout: PointLayout) -> wp.array:
        rays = self.pixel_rays(camera, R_m2c, t_m2c_m)
        with wp.ScopedDevice(self.device):
            hits = wp.empty(layout.n_points, dtype=wp.uint8)
            wp.launch(
                bound_kernels.anyhit_points,
                dim=layout.n_points,
                inputs=[self.wp_mesh.id, rays, layout],
                outputs=[hits],
            )
        return hits


class RasterRenderer(Renderer):
    """Kernel #1 with each triangle testing the pixel rays its projection covers (kernels/raster.py);
    faster on a CPU (docs/performance.md, "Raster form of kernel #1"). Its silhouette is the same face
    tests at the feature points' pixels (kernels/raster.py: splat_points)."""

    name = "raster"

    @property
    def cull_back_faces(self) -> bool:
        """Back faces are skipped on a closed, outward mesh: seen from outside, a ray's nearest hit is
        on a front face; an open mesh keeps them."""
        return self.dmesh.closed_surface

    def _render(self, rays: PixelRays, batch: RenderedBatch, n_pix: int, shading: Shading) -> None:
        look = self.dmesh.look
        key = wp.full(n_pix, raster_kernels.NO_HIT, dtype=wp.int64)
        self._per_face(raster_kernels.splat_faces, batch.n, rays, [batch.box, batch.pix_off], key)
        uv = wp.empty(n_pix if look.use_texture else 1, dtype=wp.vec2)
        lod = wp.empty(n_pix if look.use_texture and look.mip_levels else 1, dtype=float)
        shaded = int(shading.strength != 0.0)
        light = wp.empty(n_pix if look.use_texture and shaded else 1, dtype=float)
        wp.launch(
            raster_kernels.locate_hits,
            dim=n_pix,
            inputs=[self.dmesh.points, look, rays, batch.box, batch.pix_off, batch.n, key, shading],
            outputs=[uv, lod, light, batch.rgb, batch.mask],
        )
        if look.use_texture:
            wp.launch(
                raster_kernels.sample_hits,
                dim=n_pix,
                inputs=[look, uv, lod, light, shaded, batch.mask],
                outputs=[batch.rgb],
            )

    def silhouette(self, camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray, layout: PointLayout) -> wp.array:
        rays = self.pixel_rays(camera, R_m2c, t_m2c_m)
        with wp.ScopedDevice(self.device):
            hits = wp.zeros(layout.n_points, dtype=wp.uint8)
            self._per_face(raster_kernels.splat_points, layout.n_cand, rays, [layout], hits)
        return hits

    def _per_face(self, kernel, n_cand: int, rays: PixelRays, per_candidate: list, out: wp.array) -> None:
        """Launch a raster kernel over (candidate, face) for n_cand candidates, in chunks of at most
        VERTEX_SLOTS projected vertices: project_points, then `kernel` with the mesh, projections,
        rays (pixel_rays), the arguments `per_candidate`, the chunk's first candidate and the culling
        flag; it writes `out`."""
        points, indices = self.dmesh.points, self.dmesh.indices
        n_points = len(points)
        chunk = max(1, VERTEX_SLOTS // n_points)
        uvz = wp.empty((min(chunk, n_cand), n_points), dtype=wp.vec3)
        for c0 in range(0, n_cand, chunk):
            m = min(chunk, n_cand - c0)
            wp.launch(
                raster_kernels.project_points,
                dim=(m, n_points),
                inputs=[points, rays, c0, MIN_DEPTH_M],
                outputs=[uvz],
            )
            wp.launch(
                kernel,
                dim=(m, len(indices) // 3),
                inputs=[points, indices, uvz, rays, *per_candidate, c0, MIN_DEPTH_M, int(self.cull_back_faces)],
                outputs=[out],
            )


RENDERER_CLASSES: dict[str, type[Renderer]] = {"bvh": BvhRenderer, "raster": RasterRenderer}


def make_renderer(method: str, dmesh: DeviceMesh) -> Renderer:
    """The renderer called `method` ("bvh" or "raster") over an uploaded mesh."""
    if method not in RENDERER_CLASSES:
        raise PerchError(f"renderer method must be bvh or raster, got {method!r}")
    return RENDERER_CLASSES[method](dmesh)


def mesh_renderer(mesh: ObjectMesh, device: str, method: str = "bvh", texture: str = "bilinear") -> Renderer:
    """A renderer of its own for `mesh` on `device` (the mesh uploaded for it alone; the engine shares one)."""
    if method not in RENDERER_CLASSES:
        raise PerchError(f"renderer method must be bvh or raster, got {method!r}")
    return RENDERER_CLASSES[method](DeviceMesh(mesh, device, texture))
