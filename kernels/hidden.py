"""Points another object hides: marked after kernel #2 (and after the bound's ceiling lookup).

A candidate's feature point is *hidden* when the photo's occluder map (perch_warp.hidden: per feature-grid
cell, the camera distance of the nearest other object whose silhouette covers that cell's pixel; +inf
where none does) holds a distance below the candidate's own (its model origin's distance from the
camera, metres). Nearer objects hide farther ones: objects standing on a table rarely interleave, the
comparison perch_warp/joint.py makes between answers. A hidden point keeps its place in the silhouette
(it counts towards N, the object's size) but its value becomes HIDDEN, which the reduction
(kernels/reduce.py) tells from both a compared value and NOT_ON_MASK.
"""

import warp as wp

from .features import NOT_ON_MASK, PointLayout, feature_point, in_box

# A hidden point's value: above NOT_ON_MASK / 2 (it is on the silhouette), far below any real value.
HIDDEN = -1.0e28
# Visible values lie above this; hidden ones between it and NOT_ON_MASK / 2.
HIDDEN_BELOW = HIDDEN / 2.0


@wp.kernel(enable_backward=False)
def hide_points(
    pts: PointLayout,
    near_m: wp.array2d(dtype=float),
    distance_m: wp.array(dtype=float),
    n_blocks: int,
    values: wp.array(dtype=float),
):
    """values[s n_points + i] = HIDDEN for every block s where point i is on its candidate's silhouette
    and the occluder map near_m at its grid cell is below the candidate's distance_m[c]; points beyond
    the photo's grid (value 0, nothing to compare) and off the silhouette stay as they are."""
    i = wp.tid()
    c, gx, gy, u, v = feature_point(pts, i)
    if not in_box(wp.vec4i(0, 0, near_m.shape[1], near_m.shape[0]), gx, gy):
        return
    if near_m[gy, gx] >= distance_m[c]:
        return
    for s in range(n_blocks):
        j = s * pts.n_points + i
        if values[j] > NOT_ON_MASK / 2.0:
            values[j] = HIDDEN
