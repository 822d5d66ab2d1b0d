"""Kernel #2: conv1 features and rarity-weighted cosine similarity.

A feature point is a pixel (u, v) = (half + s*gx, half + s*gy) of the global feature
grid (stride s, half = ks // 2), so every 11x11 window lies inside the image and the
photo's feature map equals a stride-s, unpadded convolution of the photo.

The grid extends beyond the image: a candidate's silhouette points outside the photo
count towards its size with score 0, so α stays the fraction of the *object* that
must be visible, and a pose mostly outside the picture cannot win on a few points.

The candidate's image is never materialised: a window pixel takes the rendered
colour where the candidate's mask covers it and the photo's colour elsewhere
(compositing onto the observed image, thesis §3.2.1).

Weights arrive folded with the network's preprocessing (they act on RGB in [0, 1])
and tap-major: Wt[(dy * ks + dx) * 3 + ch_in] is a C-vector over output channels,
so the inner loop is one C-wide multiply-add that compilers vectorise.

Kernels are generated per channel count C (64 for torchvision, 96 for Caffe).
"""

import functools

import warp as wp

from .render import find_candidate

# Marks feature points that are not on the candidate's mask; far below any score.
NOT_ON_MASK = -1.0e30


@wp.func
def feature_point(
    pt_off: wp.array(dtype=wp.int32), n_cand: int, gbox: wp.array(dtype=wp.vec4i), ks: int, stride: int, i: int
):
    """Flat feature point i: its candidate c, grid cell (gx, gy) and pixel (u, v). Candidate c owns
    points [pt_off[c], pt_off[c+1]), its grid box gbox[c] = (gx0, gy0, gw, gh) row by row; kernel #2
    and the silhouette bound (kernels/bound.py) both walk the points in this order."""
    c = find_candidate(pt_off, n_cand, i)
    g = gbox[c]
    local = i - pt_off[c]
    gx = g[0] + local % g[2]
    gy = g[1] + local // g[2]
    half = ks // 2
    return c, gx, gy, half + stride * gx, half + stride * gy


@wp.func
def in_box(b: wp.vec4i, x: int, y: int) -> bool:
    """Pixel (x, y) inside the box (x0, y0, w, h)."""
    return x >= b[0] and x < b[0] + b[2] and y >= b[1] and y < b[1] + b[3]


@functools.cache
def feature_kernels(C: int):
    """(observed_features, score_points) kernels for C output channels."""
    vecC = wp.types.vector(length=C, dtype=wp.float32)

    @wp.func
    def conv_at(
        image: wp.array2d(dtype=wp.vec3),
        rgb: wp.array(dtype=wp.vec3),
        mask: wp.array(dtype=wp.uint8),
        roff: int,
        rb: wp.vec4i,
        u: int,
        v: int,
        Wt: wp.array(dtype=vecC),
        bias: vecC,
        ks: int,
        relu: int,
    ) -> vecC:
        half = ks // 2
        acc = bias
        for dy in range(ks):
            y = v + dy - half
            for dx in range(ks):
                x = u + dx - half
                p = image[y, x]
                if in_box(rb, x, y):
                    j = roff + (y - rb[1]) * rb[2] + (x - rb[0])
                    if mask[j] != wp.uint8(0):
                        p = rgb[j]
                k = (dy * ks + dx) * 3
                acc = acc + Wt[k] * p[0] + Wt[k + 1] * p[1] + Wt[k + 2] * p[2]
        if relu != 0:
            for ch in range(C):
                acc[ch] = wp.max(acc[ch], 0.0)
        return acc

    @wp.kernel(enable_backward=False, module="unique")
    def observed_features(
        image: wp.array2d(dtype=wp.vec3),
        Wt: wp.array(dtype=vecC),
        bias: vecC,
        ks: int,
        stride: int,
        relu: int,
        dummy_rgb: wp.array(dtype=wp.vec3),
        dummy_mask: wp.array(dtype=wp.uint8),
        out: wp.array2d(dtype=vecC),
    ):
        gy, gx = wp.tid()
        half = ks // 2
        no_box = wp.vec4i(0, 0, 0, 0)
        out[gy, gx] = conv_at(
            image, dummy_rgb, dummy_mask, 0, no_box, half + stride * gx, half + stride * gy, Wt, bias, ks, relu
        )

    @wp.kernel(enable_backward=False, module="unique")
    def score_points(
        image: wp.array2d(dtype=wp.vec3),
        rgb: wp.array(dtype=wp.vec3),
        mask: wp.array(dtype=wp.uint8),
        pix_off: wp.array(dtype=wp.int32),
        box: wp.array(dtype=wp.vec4i),
        gbox: wp.array(dtype=wp.vec4i),
        pt_off: wp.array(dtype=wp.int32),
        n_cand: int,
        Wt: wp.array(dtype=vecC),
        bias: vecC,
        ks: int,
        stride: int,
        relu: int,
        obs_feat: wp.array2d(dtype=vecC),
        obs_norm: wp.array2d(dtype=float),
        rarity: wp.array2d(dtype=float),
        out: wp.array(dtype=float),
    ):
        i = wp.tid()
        c, gx, gy, u, v = feature_point(pt_off, n_cand, gbox, ks, stride, i)
        rb = box[c]
        on_mask = int(0)
        if in_box(rb, u, v):
            if mask[pix_off[c] + (v - rb[1]) * rb[2] + (u - rb[0])] != wp.uint8(0):
                on_mask = 1
        if on_mask == 0:
            out[i] = NOT_ON_MASK
            return
        if not in_box(wp.vec4i(0, 0, obs_feat.shape[1], obs_feat.shape[0]), gx, gy):
            # Silhouette beyond the photo's feature grid: part of the object, but nothing to compare.
            out[i] = 0.0
            return
        f = conv_at(image, rgb, mask, pix_off[c], rb, u, v, Wt, bias, ks, relu)
        denom = wp.length(f) * obs_norm[gy, gx]
        cos = float(0.0)
        if denom > 1.0e-12:
            cos = wp.dot(f, obs_feat[gy, gx]) / denom
        out[i] = cos * rarity[gy, gx]

    return vecC, observed_features, score_points
