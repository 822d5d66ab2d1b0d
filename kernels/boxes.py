"""Candidates' pixel boxes on the device: one thread per candidate projects the mesh's hull points.

The same arithmetic as perch_warp.render.project_boxes (the NumPy reference), in
float64 so that floor/ceil land on the same integers: (x0, y0, w, h) covering the
projection, not clipped to the image; 0s where it misses the image; -1s where a hull
point is closer than min_depth to the camera plane.
"""

import warp as wp

# No fused multiply-adds: NumPy rounds each product, and the boxes must match it to the pixel.
wp.set_module_options({"fuse_fp": False})


@wp.kernel(enable_backward=False)
def project_boxes(
    hull_m: wp.array(dtype=wp.vec3d),
    rot_m2c: wp.array(dtype=wp.mat33d),
    t_m2c_m: wp.array(dtype=wp.vec3d),
    fx: wp.float64,
    fy: wp.float64,
    cx: wp.float64,
    cy: wp.float64,
    width: int,
    height: int,
    min_depth: wp.float64,
    out: wp.array(dtype=wp.vec4i),
):
    c = wp.tid()
    R = rot_m2c[c]
    t = t_m2c_m[c]
    behind = int(0)
    umin = wp.float64(wp.inf)
    umax = wp.float64(-wp.inf)
    vmin = wp.float64(wp.inf)
    vmax = wp.float64(-wp.inf)
    for k in range(hull_m.shape[0]):
        p = R * hull_m[k] + t
        z = p[2]
        if z < min_depth:
            behind = 1
            z = min_depth
        u = fx * p[0] / z + cx
        v = fy * p[1] / z + cy
        umin = wp.min(umin, u)
        umax = wp.max(umax, u)
        vmin = wp.min(vmin, v)
        vmax = wp.max(vmax, v)
    if behind != 0:
        out[c] = wp.vec4i(-1, -1, -1, -1)
        return
    x0 = wp.floor(umin)
    x1 = wp.ceil(umax)
    y0 = wp.floor(vmin)
    y1 = wp.ceil(vmax)
    if x1 < wp.float64(0.0) or y1 < wp.float64(0.0) or x0 > wp.float64(width - 1) or y0 > wp.float64(height - 1):
        out[c] = wp.vec4i(0, 0, 0, 0)
        return
    out[c] = wp.vec4i(int(x0), int(y0), int(x1 - x0) + 1, int(y1 - y0) + 1)
