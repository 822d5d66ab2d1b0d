"""Microbenchmark kernel: pure ray casting through the engine's `wp.Mesh` (model frame, metres).

One thread per (pose, pixel) of the full image; the ray is kernel #1's own (render.pixel_ray_m:
camera direction (u - cx)/fx, (v - cy)/fy, 1 turned into the model frame),
and only the hit parameter is written, so the timing is the BVH traversal and
triangle tests alone (no texture lookup, no packing by boxes).
"""

import warp as wp

from ..kernels.render import PixelRays, pixel_ray_m

# Written where a ray meets nothing.
MISS = -1.0


@wp.kernel(enable_backward=False)
def cast_depth(
    mesh: wp.uint64,
    rays: PixelRays,
    out_t: wp.array3d(dtype=float),
):
    """out_t[p, v, u] = ray parameter of the first hit (the camera-frame depth, m, since the direction's z is 1)."""
    p, v, u = wp.tid()
    q = wp.mesh_query_ray(mesh, rays.origin_m[p], pixel_ray_m(rays, p, u, v), 1.0e6)
    if q.result:
        out_t[p, v, u] = q.t
    else:
        out_t[p, v, u] = MISS
