"""Kernel #1, raster form: kernel #1's pixel rays, tested per triangle instead of through the BVH.

A BVH query walks the tree for every ray, and on a CPU that walk is the render's cost
(docs/performance.md, "Where a CPU render's time goes"). Here each triangle of each
candidate tests only the pixel rays its projection can cover, with the ray-triangle test
Warp's mesh query runs (`wp::intersect_ray_tri_woop`, called natively so the arithmetic
is the same), and keeps each pixel's nearest hit as a 64-bit key (distance bits, then
face) that an atomic compare-and-swap loop resolves on any device. Two shading passes then
colour each pixel from its face as kernel #1 does. Same layout as kernel #1: candidates' boxes packed flat
(pix_off), rays in the model frame (metres), camera frame for the projections.
"""

import warp as wp

from .features import PointLayout
from .render import (
    MeshLook,
    PixelRays,
    Shading,
    box_pixel,
    light_factor,
    lit,
    pixel_ray_m,
    sample_mip,
    sample_texture,
    surface_uv,
    texture_lod,
    vertex_color,
)

# Key of a pixel no triangle covers (above any hit's key).
NO_HIT = wp.constant(wp.int64(0x7FFFFFFFFFFFFFFF))
# Slack (pixels) of the screen-space tests, which only skip rays that cannot hit: projections are
# computed in the camera frame and the ray test in the model frame, and the two round differently
# (by about 1e-4 px here).
SLACK_PX = wp.constant(0.05)
# The edge pre-test needs edges that are not too short (absolute, and against the longest edge):
# a point's distance to a short edge's line magnifies the rounding of its corners.
MIN_EDGE_PX = wp.constant(0.25)
MAX_EDGE_RATIO = wp.constant(64.0)
# Faces whose projection has more than this area (pixels², y down; times 1 + the face's extent in
# pixels) facing away are skipped when the mesh is closed: from outside a closed surface the nearest
# hit is always on a face turned towards the ray.
BACK_FACE_AREA_PX2 = wp.constant(1.0e-3)


@wp.func_native(
    """
float t, u, v, s;
if (wp::intersect_ray_tri_woop(p, d, a, b, c, t, u, v, s, nullptr) && t >= 0.0f)
    return wp::vec4(1.0f, t + 0.0f, u, v);  // + 0.0f: no -0.0, whose bits would sort first
return wp::vec4(0.0f, 0.0f, 0.0f, 0.0f);
"""
)
def ray_triangle(p: wp.vec3, d: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec4:
    """(hit, t, u, v): Warp's mesh-query test of ray p + t d against triangle (a, b, c), t >= 0."""
    ...


@wp.func_native(
    """
union { float f; wp::int32 i; } bits;
bits.f = x;
return bits.i;
"""
)
def float_bits(x: float) -> wp.int32:
    """The IEEE-754 bits of x: for x >= 0 they order as x does."""
    ...


@wp.func
def hit_key(t: float, face: int) -> wp.int64:
    """Nearest first, then the lower face index: the minimum key is the hit a pixel keeps."""
    return (wp.int64(float_bits(t)) << wp.int64(32)) | wp.int64(face)


@wp.func
def keep_nearest(keys: wp.array(dtype=wp.int64), i: int, key: wp.int64):
    """keys[i] = min(keys[i], key), atomically: a compare-and-swap loop, since Warp's CUDA atomic
    min takes 32-bit integers only."""
    old = keys[i]
    while key < old:
        seen = wp.atomic_cas(keys, i, old, key)
        if seen == old:
            break
        old = seen


@wp.func
def edge_line(p: wp.vec3, q: wp.vec3) -> wp.vec3:
    """Line through projected corners p, q (pixels) as (n_x, n_y, w) with n the unit normal, so that
    n . x + w is the signed distance of x from it (the direction of n depends on the winding)."""
    e = wp.vec2(q[0] - p[0], q[1] - p[1])
    n = wp.vec2(-e[1], e[0]) / wp.max(wp.length(e), 1.0e-20)
    return wp.vec3(n[0], n[1], -(n[0] * p[0] + n[1] * p[1]))


@wp.func
def face_window(q0: wp.vec3, q1: wp.vec3, q2: wp.vec3, b: wp.vec4i, min_depth_m: float, cull_back: int):
    """Face (projected corners q_k = (u, v, depth)) in box b = (x0, y0, w, h): whether it is tested at
    all (0 for a face turned away when cull_back) and the pixel range (u0, v0, u1, v1) its rays may hit."""
    window = wp.vec4i(b[0], b[1], b[0] + b[2] - 1, b[1] + b[3] - 1)
    # A corner too near the camera projects nowhere sensible: then every ray of the box is tested.
    if wp.min(wp.min(q0[2], q1[2]), q2[2]) < min_depth_m:
        return 1, window
    if cull_back != 0:
        area = (q1[0] - q0[0]) * (q2[1] - q0[1]) - (q1[1] - q0[1]) * (q2[0] - q0[0])
        # The projection's rounding moves the area by about 1e-4 px times the face's extent: only
        # faces clearly turned away are skipped, never one seen nearly edge-on.
        extent = wp.max(
            wp.max(wp.max(q0[0], q1[0]), q2[0]) - wp.min(wp.min(q0[0], q1[0]), q2[0]),
            wp.max(wp.max(q0[1], q1[1]), q2[1]) - wp.min(wp.min(q0[1], q1[1]), q2[1]),
        )
        if area > BACK_FACE_AREA_PX2 * (1.0 + extent):
            return 0, window
    window = wp.vec4i(
        wp.max(window[0], int(wp.ceil(wp.min(wp.min(q0[0], q1[0]), q2[0]) - SLACK_PX))),
        wp.max(window[1], int(wp.ceil(wp.min(wp.min(q0[1], q1[1]), q2[1]) - SLACK_PX))),
        wp.min(window[2], int(wp.floor(wp.max(wp.max(q0[0], q1[0]), q2[0]) + SLACK_PX))),
        wp.min(window[3], int(wp.floor(wp.max(wp.max(q0[1], q1[1]), q2[1]) + SLACK_PX))),
    )
    return 1, window


@wp.func
def face_lines(q0: wp.vec3, q1: wp.vec3, q2: wp.vec3, min_depth_m: float):
    """The face's edge lines (rows, see edge_line) and whether they may be used to skip pixels
    (all corners projected, edges neither too short nor too unequal)."""
    lines = wp.matrix_from_rows(edge_line(q0, q1), edge_line(q1, q2), edge_line(q2, q0))
    l0 = wp.length(wp.vec2(q1[0] - q0[0], q1[1] - q0[1]))
    l1 = wp.length(wp.vec2(q2[0] - q1[0], q2[1] - q1[1]))
    l2 = wp.length(wp.vec2(q0[0] - q2[0], q0[1] - q2[1]))
    shortest = wp.min(wp.min(l0, l1), l2)
    usable = shortest >= MIN_EDGE_PX and shortest * MAX_EDGE_RATIO >= wp.max(wp.max(l0, l1), l2)
    usable = usable and wp.min(wp.min(q0[2], q1[2]), q2[2]) >= min_depth_m
    return lines, wp.where(usable, 1, 0)


@wp.func
def outside(lines: wp.mat33, u: int, v: int) -> bool:
    """Pixel (u, v) clearly outside the face: beyond the slack on the wrong side of an edge for
    either winding. Its ray cannot hit the face."""
    d = lines * wp.vec3(float(u), float(v), 1.0)
    return wp.min(wp.min(d[0], d[1]), d[2]) < -SLACK_PX and wp.max(wp.max(d[0], d[1]), d[2]) > SLACK_PX


@wp.func
def face_corners(indices: wp.array(dtype=wp.int32), uvz: wp.array2d(dtype=wp.vec3), j: int, f: int):
    """Face f's vertex indices and its corners as projected for chunk candidate j (project_points)."""
    i0 = indices[f * 3 + 0]
    i1 = indices[f * 3 + 1]
    i2 = indices[f * 3 + 2]
    return i0, i1, i2, uvz[j, i0], uvz[j, i1], uvz[j, i2]


@wp.kernel(enable_backward=False)
def project_points(
    points: wp.array(dtype=wp.vec3),
    rays: PixelRays,
    c0: int,
    min_depth_m: float,
    out_uvz: wp.array2d(dtype=wp.vec3),
):
    """Thread (j, k): vertex k of candidate c0 + j in pixels (u, v) and its depth z (camera frame, m)."""
    j, k = wp.tid()
    c = c0 + j
    p = wp.transpose(rays.rot_c2m[c]) * (points[k] - rays.origin_m[c])
    z = wp.max(p[2], min_depth_m)
    out_uvz[j, k] = wp.vec3(rays.fx * p[0] / z + rays.cx, rays.fy * p[1] / z + rays.cy, p[2])


@wp.kernel(enable_backward=False)
def splat_faces(
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    uvz: wp.array2d(dtype=wp.vec3),
    rays: PixelRays,
    box: wp.array(dtype=wp.vec4i),
    pix_off: wp.array(dtype=wp.int32),
    c0: int,
    min_depth_m: float,
    cull_back: int,
    out_key: wp.array(dtype=wp.int64),
):
    """Thread (j, f): cast the pixel rays of candidate c0 + j's box that face f's projection may cover."""
    j, f = wp.tid()
    c = c0 + j
    i0, i1, i2, q0, q1, q2 = face_corners(indices, uvz, j, f)
    b = box[c]
    tested, window = face_window(q0, q1, q2, b, min_depth_m, cull_back)
    if tested == 0 or window[0] > window[2] or window[1] > window[3]:
        return
    lines, use_lines = face_lines(q0, q1, q2, min_depth_m)
    a = points[i0]
    bb = points[i1]
    cc = points[i2]
    o = rays.origin_m[c]
    for v in range(window[1], window[3] + 1):
        row = pix_off[c] + (v - b[1]) * b[2] - b[0]
        for u in range(window[0], window[2] + 1):
            if use_lines != 0:
                if outside(lines, u, v):
                    continue
            h = ray_triangle(o, pixel_ray_m(rays, c, u, v), a, bb, cc)
            if h[0] > 0.0:
                keep_nearest(out_key, row + u, hit_key(h[1], f))


@wp.kernel(enable_backward=False)
def splat_points(
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    uvz: wp.array2d(dtype=wp.vec3),
    rays: PixelRays,
    pts: PointLayout,
    c0: int,
    min_depth_m: float,
    cull_back: int,
    out_hit: wp.array(dtype=wp.uint8),
):
    """Thread (j, f): mark the feature points of candidate c0 + j (its grid box and pixel box in `pts`,
    kernel #2's layout) whose pixel ray hits face f. A point is marked exactly when splat_faces
    finds a hit at its pixel: the same faces, rays and test; any hit will do."""
    j, f = wp.tid()
    c = c0 + j
    i0, i1, i2, q0, q1, q2 = face_corners(indices, uvz, j, f)
    tested, window = face_window(q0, q1, q2, pts.box[c], min_depth_m, cull_back)
    if tested == 0:
        return
    g = pts.gbox[c]
    half = pts.ks // 2
    stride = pts.stride
    # Feature points are the pixels (half + stride gx, half + stride gy) of grid box g.
    gx0 = wp.max(g[0], int(wp.ceil(float(window[0] - half) / float(stride))))
    gx1 = wp.min(g[0] + g[2] - 1, int(wp.floor(float(window[2] - half) / float(stride))))
    gy0 = wp.max(g[1], int(wp.ceil(float(window[1] - half) / float(stride))))
    gy1 = wp.min(g[1] + g[3] - 1, int(wp.floor(float(window[3] - half) / float(stride))))
    if gx0 > gx1 or gy0 > gy1:
        return  # no feature point in reach: most faces, at stride 4
    lines, use_lines = face_lines(q0, q1, q2, min_depth_m)
    a = points[i0]
    bb = points[i1]
    cc = points[i2]
    o = rays.origin_m[c]
    for gy in range(gy0, gy1 + 1):
        v = half + stride * gy
        row = pts.pt_off[c] + (gy - g[1]) * g[2] - g[0]
        for gx in range(gx0, gx1 + 1):
            if out_hit[row + gx] != wp.uint8(0):
                continue  # already on the silhouette
            u = half + stride * gx
            if use_lines != 0:
                if outside(lines, u, v):
                    continue
            if ray_triangle(o, pixel_ray_m(rays, c, u, v), a, bb, cc)[0] > 0.0:
                out_hit[row + gx] = wp.uint8(1)


@wp.kernel(enable_backward=False)
def locate_hits(
    points: wp.array(dtype=wp.vec3),
    look: MeshLook,
    rays: PixelRays,
    box: wp.array(dtype=wp.vec4i),
    pix_off: wp.array(dtype=wp.int32),
    n_cand: int,
    key: wp.array(dtype=wp.int64),
    shading: Shading,
    out_uv: wp.array(dtype=wp.vec2),
    out_lod: wp.array(dtype=float),
    out_light: wp.array(dtype=float),
    out_rgb: wp.array(dtype=wp.vec3),
    out_mask: wp.array(dtype=wp.uint8),
):
    """Pixel i: its nearest face's hit again (the same test, so the same barycentrics as in the
    search), and there the texture coordinates (and with mip-mapping the mip level, as kernel #1
    computes it) and, when shaded, the light's factor (Shading), or the lit vertex colour of an
    untextured mesh."""
    i = wp.tid()
    k = key[i]
    out_rgb[i] = wp.vec3(0.0, 0.0, 0.0)
    if k == NO_HIT:
        out_mask[i] = wp.uint8(0)
        return
    f = int(k & wp.int64(0x7FFFFFFF))
    c, u, v = box_pixel(pix_off, box, n_cand, i)
    ray = pixel_ray_m(rays, c, u, v)
    h = ray_triangle(
        rays.origin_m[c],
        ray,
        points[look.indices[f * 3 + 0]],
        points[look.indices[f * 3 + 1]],
        points[look.indices[f * 3 + 2]],
    )
    out_mask[i] = wp.uint8(1)
    light = light_factor(shading, look.indices, f, h[2], h[3])
    if look.use_texture != 0:
        out_uv[i] = surface_uv(look.indices, look.uvs, f, h[2], h[3])
        if look.mip_levels > 0:
            out_lod[i] = texture_lod(look, f, h[1], ray, wp.sqrt(rays.fx * rays.fy))
        if shading.strength != 0.0:
            out_light[i] = light
    else:
        out_rgb[i] = lit(vertex_color(look.indices, look.colors, f, h[2], h[3]), light)


@wp.kernel(enable_backward=False)
def sample_hits(
    look: MeshLook,
    uv: wp.array(dtype=wp.vec2),
    lod: wp.array(dtype=float),
    light: wp.array(dtype=float),
    shaded: int,
    mask: wp.array(dtype=wp.uint8),
    out_rgb: wp.array(dtype=wp.vec3),
):
    """Pixel i: the texture at its coordinates (at its mip level with mip-mapping), lit by its light
    factor when `shaded` (locate_hits wrote it). A pass of its
    own because texture reads miss the cache: with the addresses known up front, a CPU overlaps the
    misses of many pixels."""
    i = wp.tid()
    if mask[i] != wp.uint8(0):
        rgb = wp.vec3()
        if look.mip_levels > 0:
            rgb = sample_mip(look, uv[i], lod[i])
        else:
            rgb = sample_texture(look.texture, uv[i])
        if shaded != 0:
            rgb = lit(rgb, light[i])
        out_rgb[i] = rgb
