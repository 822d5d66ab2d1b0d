"""Kernel #2: conv1 features and rarity-weighted cosine similarity.

A feature point is a pixel (u, v) = (half + s*gx, half + s*gy) of the global feature
grid (stride s, half = ks // 2), so every 11x11 window lies inside the image and the
photo's feature map equals a stride-s, unpadded convolution of the photo.

The grid extends beyond the image: a candidate's silhouette points outside the photo
count towards its size with score 0, so α stays the fraction of the *object* that
must be visible, and a pose mostly outside the picture cannot win on a few points.

The candidate's image is never materialised: a window pixel takes the rendered
colour where the candidate's mask covers it and, elsewhere, the photo's colour
(compositing onto the observed image, thesis §3.2.1) or a fill colour (`Surround`:
the preprocessing mean, so that only the render counts; perch_warp.score_terms).

A point's value is cos(R, I) * gain - offset, with the photo's per-point maps `PointWeights`
(gain = rarity, offset = what the background alone earns; 0 for the thesis's score), plus, with the
outline term (weight w > 0, perch_warp.outline), w * |e(b) . n| at a point of the candidate's outline:
b the nearest pixel off its mask within one stride along the image axes, n the outward normal the mask
gives there, e the photo's normalised intensity gradient at b. With shifts
(the grid stage's tolerance, perch_warp.score_terms `shift`), a point is also compared with the
photo's feature d = (dx, dy) grid cells away, for every d of `shifts`: value s of point i lands at
out[s * n_points + i], so each shift's values are laid out like the unshifted ones.

With the light term (`Exposure`, perch_warp.score_terms `light`) every window, the photo's and the
candidate's composited one, is scaled towards one mean brightness before conv1; off (gamma 0) the
arithmetic is the thesis's, bit for bit.

Weights arrive folded with the network's preprocessing (they act on RGB in [0, 1])
and tap-major: Wt[(dy * ks + dx) * 3 + ch_in] is a C-vector over output channels,
so the inner loop is one C-wide multiply-add that compilers vectorise.

The convolution has two forms with the same points and the same result up to float
rounding (perch_warp.score, `conv`): "warp" convolves each point's window in
`score_points`; "torch" composites each candidate's windows into one crop
(`composite_crops`), convolves the crops with torch's conv2d, and `score_features`
takes the features from there.

Kernels are generated per channel count C (64 for torchvision, 96 for Caffe).
"""

import functools

import warp as wp

from .render import RenderedBoxes, find_candidate, lit

# Marks feature points that are not on the candidate's mask; far below any score.
NOT_ON_MASK = -1.0e30


@wp.struct
class Surround:
    """What a candidate's windows see beyond its mask: the photo (use_fill 0) or the colour fill
    (RGB in [0, 1]); with by_fraction 1 a point's cosine is weighted by the share of its window
    that the candidate covers, so a window mostly made of the photo cannot borrow its match."""

    use_fill: int
    fill: wp.vec3
    by_fraction: int


@wp.struct
class Exposure:
    """How a window's brightness is read (the score term `light`, perch_warp.score_terms): with gamma 0
    (the thesis's) conv1 sees the window as it is; otherwise the window is scaled by
    (ref / max(L, floor))^gamma before conv1, L its mean over pixels and channels (RGB in [0, 1]),
    so a shadowed or dim surface reads like a lit one (gamma 1: every window at mean brightness ref).
    conv1 is linear, so that is the bias plus the scaled response of the unbiased filters."""

    gamma: float
    ref: float
    floor: float


@wp.struct
class PointLayout:
    """Candidates' feature points, flat: candidate c (of n_cand) owns points [pt_off[c], pt_off[c+1])
    of its grid box gbox[c] = (gx0, gy0, gw, gh), row by row, n_points in all; grid cell (gx, gy) is
    pixel (ks // 2 + stride gx, ks // 2 + stride gy), on the candidate only inside its pixel box
    box[c] = (x0, y0, w, h). Kernel #2, the bound (kernels/bound.py) and the raster silhouette
    (kernels/raster.py: splat_points) take this one struct, so they all see the same points. The
    rendered mask is not part of it (kernel #2 takes RenderedBoxes beside it): the bound walks the
    same points before anything is rendered."""

    box: wp.array(dtype=wp.vec4i)
    gbox: wp.array(dtype=wp.vec4i)
    pt_off: wp.array(dtype=wp.int32)
    n_cand: int
    n_points: int  # pt_off[n_cand], kept for the host's launch size
    ks: int
    stride: int


@wp.func
def feature_point(pts: PointLayout, i: int):
    """Flat feature point i of `pts`: its candidate c, grid cell (gx, gy) and pixel (u, v); kernel #2
    and the silhouette bound (kernels/bound.py) both walk the points in this order."""
    c = find_candidate(pts.pt_off, pts.n_cand, i)
    g = pts.gbox[c]
    local = i - pts.pt_off[c]
    gx = g[0] + local % g[2]
    gy = g[1] + local // g[2]
    half = pts.ks // 2
    return c, gx, gy, half + pts.stride * gx, half + pts.stride * gy


@wp.func
def in_box(b: wp.vec4i, x: int, y: int) -> bool:
    """Pixel (x, y) inside the box (x0, y0, w, h)."""
    return x >= b[0] and x < b[0] + b[2] and y >= b[1] and y < b[1] + b[3]


@wp.func
def on_mask(mask: wp.array(dtype=wp.uint8), roff: int, rb: wp.vec4i, u: int, v: int) -> bool:
    """Pixel (u, v) is on the candidate's mask (its box rb, packed from roff)."""
    if in_box(rb, u, v):
        return mask[roff + (v - rb[1]) * rb[2] + (u - rb[0])] != wp.uint8(0)
    return False


@wp.func
def covered_fraction(mask: wp.array(dtype=wp.uint8), roff: int, rb: wp.vec4i, u: int, v: int, ks: int) -> float:
    """Share of the ks x ks window centred on pixel (u, v) that is on the candidate's mask."""
    half = ks // 2
    n = int(0)
    for dy in range(ks):
        for dx in range(ks):
            if on_mask(mask, roff, rb, u + dx - half, v + dy - half):
                n += 1
    return float(n) / float(ks * ks)


@wp.func
def window_share(sur: Surround, mask: wp.array(dtype=wp.uint8), roff: int, rb: wp.vec4i, u: int, v: int, ks: int):
    """What a point's cosine is weighted by: its window's covered fraction with by_fraction, else 1."""
    if sur.by_fraction != 0:
        return covered_fraction(mask, roff, rb, u, v, ks)
    return float(1.0)


@wp.func
def outline_at(mask: wp.array(dtype=wp.uint8), roff: int, rb: wp.vec4i, u: int, v: int, reach: int):
    """Whether on-mask pixel (u, v) lies on the candidate's outline: some pixel off the mask within
    `reach` pixels along +x, -x, +y or -y. Returns that, the nearest such pixel b (the first direction
    in that order on a tie) and the outward normal (unnormalised): the sum of the directions that
    leave the mask, each weighted by (reach + 1 - t) / reach for its first off pixel t away."""
    nx = float(0.0)
    ny = float(0.0)
    best = reach + 1
    bx = u
    by = v
    for k in range(4):
        dx = int(0)
        dy = int(0)
        if k == 0:
            dx = 1
        elif k == 1:
            dx = -1
        elif k == 2:
            dy = 1
        else:
            dy = -1
        t = reach + 1
        for step in range(1, reach + 1):
            if t > reach:
                if not on_mask(mask, roff, rb, u + step * dx, v + step * dy):
                    t = step
        if t <= reach:
            wgt = float(reach + 1 - t) / float(reach)
            nx += wgt * float(dx)
            ny += wgt * float(dy)
            if t < best:
                best = t
                bx = u + t * dx
                by = v + t * dy
    return best <= reach, bx, by, wp.vec2(nx, ny)


@wp.func
def outline_credit(edge: wp.array2d(dtype=wp.vec2), bx: int, by: int, normal: wp.vec2) -> float:
    """|e(b) . n / |n||: the photo's normalised gradient at pixel b across the outline's normal; 0 where b
    is beyond the photo or the normal vanishes (a part one or two pixels thin)."""
    if not in_box(wp.vec4i(0, 0, edge.shape[1], edge.shape[0]), bx, by):
        return 0.0
    n = wp.length(normal)
    if n < 1.0e-6:
        return 0.0
    return wp.abs(wp.dot(edge[by, bx], normal)) / n


@wp.struct
class Rim:
    """A point's place on the candidate's outline (outline_at): on it (on 1), its nearest pixel off the
    mask (bx, by) and the outward normal there."""

    on: int
    bx: int
    by: int
    normal: wp.vec2


@wp.struct
class PointWeights:
    """The photo's maps on its feature grid (rows, cols): a compared point scores
    cos * gain[gy, gx] - offset[gy, gx]."""

    gain: wp.array2d(dtype=float)
    offset: wp.array2d(dtype=float)
    # The outline term: the photo's normalised intensity gradient per *pixel* (H, W), |edge| < 1, and
    # its weight (0: off, the thesis's score; perch_warp.outline).
    edge: wp.array2d(dtype=wp.vec2)
    outline: float
    # The rectified term's weight b (0: off, the thesis's score): the cosine is (1 - b) cos(R, I) +
    # b cos(R+, I+), R+ and I+ the features after AlexNet's ReLU (perch_warp.score_terms `rectified`).
    rectified: float
    # The centre term's weight c (0: off): the cosine is (1 - c) cos(R, I) + c cos(R - Rm, I - Im), Rm and
    # Im the means of the candidate's features and the photo's over its compared points
    # (perch_warp.score_terms `centre`; only kernel #2's torch form, score_features, computes them).
    centre: float


@wp.func
def rim_of(
    pw: PointWeights, mask: wp.array(dtype=wp.uint8), roff: int, rb: wp.vec4i, u: int, v: int, reach: int
) -> Rim:
    """Point (u, v)'s Rim when the outline term is on (pw.outline > 0); off the outline otherwise, so the
    thesis's score does not walk the mask."""
    r = Rim()
    r.on = 0
    if pw.outline > 0.0:
        on, bx, by, normal = outline_at(mask, roff, rb, u, v, reach)
        if on:
            r.on = 1
            r.bx = bx
            r.by = by
            r.normal = normal
    return r


@wp.func
def composite(
    image: wp.array2d(dtype=wp.vec3),
    rgb: wp.array(dtype=wp.vec3),
    mask: wp.array(dtype=wp.uint8),
    roff: int,
    rb: wp.vec4i,
    x: int,
    y: int,
    sur: Surround,
) -> wp.vec3:
    """The candidate's image at pixel (x, y): rendered where its mask covers it, else the photo or the fill."""
    if in_box(rb, x, y):
        j = roff + (y - rb[1]) * rb[2] + (x - rb[0])
        if mask[j] != wp.uint8(0):
            return rgb[j]
    if sur.use_fill != 0:
        return sur.fill
    return image[y, x]


@wp.func
def point_to_compare(seen: RenderedBoxes, pts: PointLayout, grid_rows: int, grid_cols: int, i: int):
    """Flat feature point i (feature_point): whether it is compared with the photo, the value it
    scores if not, its candidate c, grid cell (gx, gy) and pixel (u, v). Not compared: off the
    candidate's rendered mask (NOT_ON_MASK), or on it but beyond the photo's feature grid (0: part
    of the object, but nothing to compare). Both forms of kernel #2 decide by this, so they score
    the same points."""
    c, gx, gy, u, v = feature_point(pts, i)
    if not on_mask(seen.mask, seen.pix_off[c], seen.box[c], u, v):
        return False, float(NOT_ON_MASK), c, gx, gy, u, v
    if not in_box(wp.vec4i(0, 0, grid_cols, grid_rows), gx, gy):
        return False, float(0.0), c, gx, gy, u, v
    return True, float(0.0), c, gx, gy, u, v


@wp.kernel(enable_backward=False)
def composite_crops(
    image: wp.array2d(dtype=wp.vec3),
    seen: RenderedBoxes,
    crop: wp.array(dtype=wp.vec4i),
    crop_off: wp.array(dtype=wp.int32),
    sur: Surround,
    part: int,
    out: wp.array(dtype=float),
):
    """Thread (c, row): that row of candidate c's crop (x0, y0, w, h), the pixels its feature points'
    windows read, packed flat from 3 crop_off[c] as 3 planes (R, G, B) of h rows. Pixels beyond the
    photo are 0: only points beyond the photo's feature grid read them, and those are not compared.
    `part` 0: the composited window; 1: its rendered pixels alone (0 elsewhere); 2: the rest alone
    (0 where rendered): conv1 is linear, so the exposure term scales part 1's response alone."""
    c, row = wp.tid()
    cr = crop[c]
    if row >= cr[3]:
        return
    y = cr[1] + row
    n = cr[2] * cr[3]
    base = 3 * crop_off[c] + row * cr[2]
    photo = wp.vec4i(0, 0, image.shape[1], image.shape[0])
    roff = seen.pix_off[c]
    rb = seen.box[c]
    for col in range(cr[2]):
        x = cr[0] + col
        p = wp.vec3(0.0, 0.0, 0.0)
        if in_box(photo, x, y):
            p = composite(image, seen.rgb, seen.mask, roff, rb, x, y, sur)
            if part != 0:
                rendered = on_mask(seen.mask, roff, rb, x, y)
                if (part == 1) != rendered:
                    p = wp.vec3(0.0, 0.0, 0.0)
        out[base + col] = p[0]
        out[base + n + col] = p[1]
        out[base + 2 * n + col] = p[2]


@wp.func
def exposure_gain(exp: Exposure, mean_lum: float) -> float:
    """The factor a window of mean brightness mean_lum is scaled by (Exposure)."""
    return wp.pow(exp.ref / wp.max(mean_lum, exp.floor), exp.gamma)


@wp.kernel(enable_backward=False)
def read_at_exposure(rgb: wp.array(dtype=wp.vec3), gain: float, out: wp.array(dtype=wp.vec3)):
    """Each rendered colour (sRGB in [0, 1]) as a camera exposed `gain` times brighter records it: the
    light is linear, the sensor clips at white (the tone term, perch_warp.score_terms)."""
    i = wp.tid()
    out[i] = lit(rgb[i], gain)


@wp.kernel(enable_backward=False)
def sums_to_means(counts: wp.array(dtype=float), per_candidate: int, sums: wp.array(dtype=float)):
    """The centre term's sums (candidate_sums: per_candidate of them per candidate) divided by their
    candidate's count of points, in place, once per candidate rather than at each of its points."""
    i = wp.tid()
    sums[i] = sums[i] / wp.max(counts[i // per_candidate], 1.0)


@functools.cache
def feature_kernels(C: int):
    """(vecC, observed_features, score_points, score_features, candidate_sums) for C output channels."""
    vecC = wp.types.vector(length=C, dtype=wp.float32)

    @wp.func
    def rectified(f: vecC, relu: int) -> vecC:
        out = f
        if relu != 0:
            for ch in range(C):
                out[ch] = wp.max(f[ch], 0.0)
        return out

    @wp.func
    def cosine(f: vecC, g: vecC) -> float:
        """cos(f, g), 0 where either vanishes."""
        denom = wp.length(f) * wp.length(g)
        cos = float(0.0)
        if denom > 1.0e-12:
            cos = wp.dot(f, g) / denom
        return cos

    @wp.func
    def weighted_cosine(
        f: vecC,
        f_norm: float,
        g: vecC,
        g_norm: float,
        pw: PointWeights,
        gx: int,
        gy: int,
        share: float,
        f_mean: vecC,
        g_mean: vecC,
    ) -> float:
        """cos(f, g) x gain - offset at grid cell (gx, gy) (f_norm, g_norm: the features' lengths), the cosine
        weighted by share (1, or the window's covered fraction); cos is 0 where either feature vanishes.
        With the rectified term, cos blends in the rectified features' cosine (PointWeights.rectified);
        with the centre term, the cosine of f - f_mean and g - g_mean (the candidate's means)."""
        denom = f_norm * g_norm
        cos = float(0.0)
        if denom > 1.0e-12:
            cos = wp.dot(f, g) / denom
        if pw.centre > 0.0:
            cos = (1.0 - pw.centre) * cos + pw.centre * cosine(f - f_mean, g - g_mean)
        if pw.rectified > 0.0:
            cos = (1.0 - pw.rectified) * cos + pw.rectified * cosine(rectified(f, 1), rectified(g, 1))
        if share < 1.0:
            cos = cos * share
        return cos * pw.gain[gy, gx] - pw.offset[gy, gx]

    @wp.func
    def compared_values(
        a: vecC,
        q: vecC,
        gains: wp.array(dtype=float),
        relu: int,
        obs_feat: wp.array2d(dtype=vecC),
        obs_norm: wp.array2d(dtype=float),
        pw: PointWeights,
        gx: int,
        gy: int,
        share: float,
        shifts: wp.array(dtype=wp.vec2i),
        n_points: int,
        i: int,
        rim: Rim,
        stride: int,
        f_mean: vecC,
        g_mean: vecC,
        out: wp.array(dtype=float),
    ):
        """out[(k S + s) n_points + i] = weighted_cosine of the point's feature f = gains[k] a + q (rectified
        with relu) with the photo's feature shifts[s] cells away from (gx, gy), plus the outline term
        there (`rim`: rim_of's); 0 where that cell is beyond the photo's feature grid (as for an
        unshifted point there). With the exposure term a is conv1's response to the window's rendered
        pixels alone and q the bias plus the rest's (conv_split), so f is the render read gains[k] times
        as bright; without it gains is (1,), a the whole response and q 0, and 1 a + 0 is a, bit for bit."""
        grid = wp.vec4i(0, 0, obs_feat.shape[1], obs_feat.shape[0])
        for k in range(gains.shape[0]):
            f = rectified(gains[k] * a + q, relu)
            f_norm = wp.length(f)  # the same for every shift
            for s in range(shifts.shape[0]):
                hx = gx + shifts[s][0]
                hy = gy + shifts[s][1]
                value = float(0.0)
                if in_box(grid, hx, hy):
                    g = obs_feat[hy, hx]
                    value = weighted_cosine(f, f_norm, g, obs_norm[hy, hx], pw, hx, hy, share, f_mean, g_mean)
                    if rim.on != 0:
                        d = shifts[s] * stride  # the whole silhouette moves: its outline pixel with it
                        value += pw.outline * outline_credit(pw.edge, rim.bx + d[0], rim.by + d[1], rim.normal)
                out[(k * shifts.shape[0] + s) * n_points + i] = value

    @wp.func
    def not_compared(value: float, n_blocks: int, n_points: int, i: int, out: wp.array(dtype=float)):
        """A point that is not compared (point_to_compare) holds the same value in every block (every
        shift and exposure gain)."""
        for s in range(n_blocks):
            out[s * n_points + i] = value

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
        sur: Surround,
        exp: Exposure,
    ) -> vecC:
        half = ks // 2
        acc = bias
        if exp.gamma != 0.0:
            acc = vecC()  # the unbiased response, scaled below
        lum = float(0.0)
        for dy in range(ks):
            y = v + dy - half
            for dx in range(ks):
                x = u + dx - half
                p = composite(image, rgb, mask, roff, rb, x, y, sur)
                k = (dy * ks + dx) * 3
                acc = acc + Wt[k] * p[0] + Wt[k + 1] * p[1] + Wt[k + 2] * p[2]
                lum += p[0] + p[1] + p[2]
        if exp.gamma != 0.0:
            acc = acc * exposure_gain(exp, lum / float(3 * ks * ks)) + bias
        return rectified(acc, relu)

    @wp.func
    def conv_split(
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
        sur: Surround,
    ):
        """conv_at's unrectified response in two parts (a, q): a to the window's rendered pixels alone,
        q the bias plus the response to the rest (photo or fill), so that a render read g times as
        bright gives g a + q (the exposure term; not with the light term, which conv_at applies)."""
        half = ks // 2
        a = vecC()
        q = bias
        for dy in range(ks):
            y = v + dy - half
            for dx in range(ks):
                x = u + dx - half
                p = composite(image, rgb, mask, roff, rb, x, y, sur)
                k = (dy * ks + dx) * 3
                w = Wt[k] * p[0] + Wt[k + 1] * p[1] + Wt[k + 2] * p[2]
                if on_mask(mask, roff, rb, x, y):
                    a = a + w
                else:
                    q = q + w
        return a, q

    @wp.kernel(enable_backward=False, module="unique")
    def observed_features(
        image: wp.array2d(dtype=wp.vec3),
        Wt: wp.array(dtype=vecC),
        bias: vecC,
        ks: int,
        stride: int,
        relu: int,
        exp: Exposure,
        dummy_rgb: wp.array(dtype=wp.vec3),
        dummy_mask: wp.array(dtype=wp.uint8),
        out: wp.array2d(dtype=vecC),
    ):
        gy, gx = wp.tid()
        half = ks // 2
        no_box = wp.vec4i(0, 0, 0, 0)
        photo_only = Surround()
        photo_only.use_fill = 0
        out[gy, gx] = conv_at(
            image,
            dummy_rgb,
            dummy_mask,
            0,
            no_box,
            half + stride * gx,
            half + stride * gy,
            Wt,
            bias,
            ks,
            relu,
            photo_only,
            exp,
        )

    @wp.kernel(enable_backward=False, module="unique")
    def score_points(
        image: wp.array2d(dtype=wp.vec3),
        seen: RenderedBoxes,
        pts: PointLayout,
        Wt: wp.array(dtype=vecC),
        bias: vecC,
        relu: int,
        exp: Exposure,
        sur: Surround,
        obs_feat: wp.array2d(dtype=vecC),
        obs_norm: wp.array2d(dtype=float),
        pw: PointWeights,
        shifts: wp.array(dtype=wp.vec2i),
        gains: wp.array(dtype=float),
        out: wp.array(dtype=float),
    ):
        i = wp.tid()
        compared, value, c, gx, gy, u, v = point_to_compare(seen, pts, obs_feat.shape[0], obs_feat.shape[1], i)
        if not compared:
            not_compared(value, shifts.shape[0] * gains.shape[0], pts.n_points, i, out)
            return
        roff = seen.pix_off[c]
        rb = seen.box[c]
        share = window_share(sur, seen.mask, roff, rb, u, v, pts.ks)
        rim = rim_of(pw, seen.mask, roff, rb, u, v, pts.stride)
        a = vecC()
        q = vecC()
        if gains.shape[0] == 1:  # no exposure term: conv_at, the thesis's arithmetic bit for bit
            a = conv_at(image, seen.rgb, seen.mask, roff, rb, u, v, Wt, bias, pts.ks, 0, sur, exp)
        else:
            a, q = conv_split(image, seen.rgb, seen.mask, roff, rb, u, v, Wt, bias, pts.ks, sur)
        none = vecC()  # no centre term in this form (FeatureScorer refuses it)
        compared_values(
            a, q, gains, relu, obs_feat, obs_norm, pw, gx, gy, share, shifts, pts.n_points, i, rim, pts.stride,
            none, none, out,
        )  # fmt: skip

    @wp.kernel(enable_backward=False, module="unique")
    def score_features(
        feat: wp.array(dtype=float),
        seen: RenderedBoxes,
        pts: PointLayout,
        relu: int,
        sur: Surround,
        obs_feat: wp.array2d(dtype=vecC),
        obs_norm: wp.array2d(dtype=float),
        pw: PointWeights,
        shifts: wp.array(dtype=wp.vec2i),
        gains: wp.array(dtype=float),
        feat_rest: wp.array(dtype=float),
        means: wp.array(dtype=float),
        out: wp.array(dtype=float),
    ):
        """score_points' values from features convolved elsewhere: candidate c's conv1 output as C
        planes of its points (row by row in its grid box) from C pts.pt_off[c] in feat; the same points
        on and off the mask, the same cosine, the same shifts. With the exposure term (gains: more
        than one), feat holds the response to the rendered pixels alone and feat_rest, laid out alike,
        the bias plus the rest's (conv_split's a and q). With the centre term, means holds each
        candidate's features' and the photo's means over its compared points (candidate_sums, then
        sums_to_means)."""
        i = wp.tid()
        compared, value, c, gx, gy, u, v = point_to_compare(seen, pts, obs_feat.shape[0], obs_feat.shape[1], i)
        if not compared:
            not_compared(value, shifts.shape[0] * gains.shape[0], pts.n_points, i, out)
            return
        first = pts.pt_off[c]
        n = pts.pt_off[c + 1] - first
        at = C * first + (i - first)
        f = vecC()
        for ch in range(C):
            f[ch] = feat[at + ch * n]
        share = window_share(sur, seen.mask, seen.pix_off[c], seen.box[c], u, v, pts.ks)
        rim = rim_of(pw, seen.mask, seen.pix_off[c], seen.box[c], u, v, pts.stride)
        q = vecC()
        if gains.shape[0] > 1:
            for ch in range(C):
                q[ch] = feat_rest[at + ch * n]
        f_mean = vecC()
        g_mean = vecC()
        if pw.centre > 0.0:
            for ch in range(C):
                f_mean[ch] = means[2 * C * c + ch]
                g_mean[ch] = means[2 * C * c + C + ch]
        compared_values(
            f, q, gains, relu, obs_feat, obs_norm, pw, gx, gy, share, shifts, pts.n_points, i, rim, pts.stride,
            f_mean, g_mean, out,
        )  # fmt: skip

    @wp.kernel(enable_backward=False, module="unique")
    def candidate_sums(
        feat: wp.array(dtype=float),
        seen: RenderedBoxes,
        pts: PointLayout,
        obs_feat: wp.array2d(dtype=vecC),
        sums: wp.array(dtype=float),
        counts: wp.array(dtype=float),
    ):
        """The centre term's first pass (feat laid out as score_features reads it): per candidate c, the
        sums of its compared points' features (sums[2 C c + ch]), of the photo's features there
        (sums[2 C c + C + ch]) and their count (counts[c]); sums and counts start at 0."""
        i = wp.tid()
        compared, value, c, gx, gy, u, v = point_to_compare(seen, pts, obs_feat.shape[0], obs_feat.shape[1], i)
        if not compared:
            return
        first = pts.pt_off[c]
        n = pts.pt_off[c + 1] - first
        at = C * first + (i - first)
        g = obs_feat[gy, gx]
        for ch in range(C):
            wp.atomic_add(sums, 2 * C * c + ch, feat[at + ch * n])
            wp.atomic_add(sums, 2 * C * c + C + ch, g[ch])
        wp.atomic_add(counts, c, 1.0)

    return vecC, observed_features, score_points, score_features, candidate_sums
