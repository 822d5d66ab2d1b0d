"""Upper bound of a candidate's score from its silhouette alone (the pruned search).

A feature point's score is cos x rarity with cos <= 1, so it is at most the photo's
rarity there (0 beyond the photo, as in kernel #2), and the top-α mean is monotone in
every value: the top-α mean of the rarity under a candidate's silhouette bounds its
score from above. The silhouette is needed only at the feature points, one ray per
point instead of one per box pixel (1/stride² of the rays), no texture, no features.

Same flat layout and point order as kernel #2 (kernels/features.py: score_points), and
the same pixel rays as kernel #1 (kernels/render.py: pixel_ray_m), so a point is on
the silhouette here exactly when it is on the rendered mask there. Each form of kernel #1
has its own silhouette: any-hit BVH rays for the bvh form, the raster form's own face tests
(kernels/raster.py: splat_points) for the raster form.
"""

import warp as wp

from .features import NOT_ON_MASK, PointLayout, feature_point, in_box
from .render import PixelRays, pixel_ray_m


@wp.func
def silhouette_rarity(rarity: wp.array2d(dtype=float), gx: int, gy: int) -> float:
    """A silhouette point's bound: the photo's rarity at grid cell (gx, gy), 0 beyond the photo (as in kernel #2)."""
    if not in_box(wp.vec4i(0, 0, rarity.shape[1], rarity.shape[0]), gx, gy):
        return 0.0
    return rarity[gy, gx]


@wp.kernel(enable_backward=False)
def anyhit_points(
    mesh: wp.uint64,
    rays: PixelRays,
    pts: PointLayout,
    out_hit: wp.array(dtype=wp.uint8),
):
    """The BVH form's silhouette: 1 where feature point i's pixel ray hits the mesh inside its
    candidate's rendered box, else 0 (kernel #2 reads the mask only inside that box)."""
    i = wp.tid()
    c, gx, gy, u, v = feature_point(pts, i)
    out_hit[i] = wp.uint8(0)
    if not in_box(pts.box[c], u, v):
        return
    # Any hit, not the closest: Warp's any-hit query runs the same ray-triangle test over the same
    # range [0, max_t) as kernel #1's closest-hit query, so it hits exactly when that one does, and
    # stops at the first triangle (about half the traversal, tools/render_cost.py).
    if wp.mesh_query_ray_anyhit(mesh, rays.origin_m[c], pixel_ray_m(rays, c, u, v), 1.0e6):
        out_hit[i] = wp.uint8(1)


@wp.kernel(enable_backward=False)
def rarity_at_hits(
    hits: wp.array(dtype=wp.uint8),
    pts: PointLayout,
    rarity: wp.array2d(dtype=float),
    out: wp.array(dtype=float),
):
    """Each feature point's bound: the ceiling map at the point where the renderer's silhouette
    (`hits`: anyhit_points for the BVH form, kernels/raster.py splat_points for the raster form,
    within the rendered box) covers it, else NOT_ON_MASK."""
    i = wp.tid()
    if hits[i] == wp.uint8(0):
        out[i] = NOT_ON_MASK
        return
    c, gx, gy, u, v = feature_point(pts, i)
    out[i] = silhouette_rarity(rarity, gx, gy)
