"""Kernel #2 against independent references: torch's conv2d and a NumPy scorer."""

import numpy as np
import pytest
import torch
import warp as wp
from _colour import srgb_exposed
from _device import DEVICE
from perch_warp.kernels.features import NOT_ON_MASK

from perch_warp.errors import PerchError
from perch_warp.features import PREPROCESSING, FeatureWeights, load_npz, smoothed
from perch_warp.outline import edge_ceiling, edge_map
from perch_warp.render import RenderedBatch
from perch_warp.score import (
    FeatureScorer,
    best_over_shifts,
    exposure_array,
    grid_boxes,
    grid_shape,
    point_weights,
    shift_array,
    top_alpha_mean,
    top_alpha_mean_device,
)
from perch_warp.score_terms import exposure_gains, tone_gains


def _torch_features(image_u8: np.ndarray, w: FeatureWeights, stride: int) -> np.ndarray:
    """The network's own recipe: normalise, then an unpadded strided conv. (rows, cols, C)."""
    x = torch.from_numpy(image_u8.astype(np.float64) / 255.0).permute(2, 0, 1)[None]
    mean = torch.tensor(w.mean, dtype=torch.float64)[None, :, None, None]
    std = torch.tensor(w.std, dtype=torch.float64)[None, :, None, None]
    y = torch.nn.functional.conv2d(
        (x - mean) / std, torch.from_numpy(w.weight).double(), torch.from_numpy(w.bias).double(), stride=stride
    )
    return y[0].permute(1, 2, 0).numpy()


@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("stride", [1, 4])
def test_photo_features_equal_torch_conv(random_weights, stride, relu):
    img = np.random.default_rng(1).integers(0, 256, (37, 45, 3), dtype=np.uint8)
    sc = FeatureScorer(random_weights, DEVICE, stride, relu=relu)
    got = sc.observed_features(sc.image_to_device(img)).numpy()
    ref = _torch_features(img, random_weights, stride)
    if relu:
        assert (ref < 0).mean() > 0.2  # the rectification has negatives to remove
        ref = np.maximum(ref, 0.0)
        assert np.all(got >= 0.0)
    assert got.shape == ref.shape == (*grid_shape(45, 37, 11, stride), 96)
    assert np.abs(got - ref).max() < 1e-3 * np.abs(ref).max()


def test_caffe_preprocessing_is_rgb255_minus_mean(caffe_weights):
    img = np.random.default_rng(2).integers(0, 256, (23, 23, 3), dtype=np.uint8)
    sc = FeatureScorer(caffe_weights, DEVICE, 4)
    got = sc.observed_features(sc.image_to_device(img)).numpy()
    x = img.astype(np.float64) - np.array([123.68, 116.78, 103.94])
    # Caffe conv1 at the first window: sum over (channel, y, x) of W * (RGB - mean), plus bias.
    ref = (caffe_weights.weight.astype(np.float64) * x[:11, :11].transpose(2, 0, 1)[None]).sum(
        (1, 2, 3)
    ) + caffe_weights.bias
    assert np.allclose(got[0, 0], ref, rtol=1e-4, atol=1e-2)


def test_smoothed_weights_equal_a_2d_gaussian_reference(random_weights):
    """score_terms' smooth: every filter plane convolved with the 2-D Gaussian, kept at k x k; a centred
    delta filter becomes the Gaussian itself, i.e. conv1 reads the window blurred."""
    assert smoothed(random_weights, 0.0) is random_weights
    sigma, k = 1.3, random_weights.kernel_size
    got = smoothed(random_weights, sigma)
    x = np.arange(-(k - 1), k)
    g2 = np.exp(-0.5 * (x[:, None] ** 2 + x[None, :] ** 2) / sigma**2)
    g2 /= g2.sum()
    W = random_weights.weight.astype(np.float64)
    ref = np.zeros_like(W)
    for i in range(k):
        for j in range(k):
            # tap (i, j) gathers every tap (a, b) of the plane, weighted by the Gaussian at their offset
            ref[:, :, i, j] = (W * g2[i - np.arange(k)[:, None] + k - 1, j - np.arange(k)[None, :] + k - 1]).sum((2, 3))
    assert np.abs(got.weight - ref).max() < 1e-5 * np.abs(ref).max()
    assert np.array_equal(got.bias, random_weights.bias) and "low-passed" in got.source
    delta = np.zeros((1, 3, k, k), np.float32)
    delta[0, 1, k // 2, k // 2] = 1.0
    plane = smoothed(FeatureWeights(delta, np.zeros(1, np.float32), (0, 0, 0), (1, 1, 1), "delta"), sigma).weight
    assert np.allclose(plane[0, 1], g2[k // 2 : k // 2 + k, k // 2 : k // 2 + k], atol=1e-7)
    assert np.abs(plane[0, [0, 2]]).max() == 0.0


def _numpy_scores(
    img,
    rgb,
    mask,
    pix_off,
    boxes,
    gboxes,
    w: FeatureWeights,
    stride,
    rarity,
    offset=None,
    fill=False,
    weighted=False,
    shift=(0, 0),
    outline=0.0,
    edge=None,
    light=0.0,
    relu=False,
    rectified=0.0,
    render_gain=1.0,
    render_tone=1.0,
    centre=0.0,
):
    """Reference: composite each window (onto the photo, or onto the preprocessing mean with fill), convolve
    in float64, cosine with the photo's feature `shift` = (dx, dy) grid cells away, times rarity there,
    minus offset there (0 where that cell is beyond the grid), plus with `outline` the outline term:
    outline * |edge(b + shift * stride) . n / |n|| at a point with a pixel off the mask within `stride`
    along +x, -x, +y, -y (b: the nearest, the first direction on a tie; n: the directions' sum weighted
    by (stride + 1 - t) / stride). With `relu` both features are rectified (AlexNet's ReLU) before the cosine,
    which is 0 where either vanishes; with `rectified` b the cosine is (1 - b) cos + b (the rectified
    features' cosine). `render_gain` g: the rendered colours read g times as bright (the exposure term);
    `render_tone` t: each rendered sRGB colour c read as srgb(min(1, t lin(c))) (the tone term);
    `centre` c: the cosine is (1 - c) cos + c cos(f - fm, fo - om), fm and om the means of the candidate's
    and the photo's (unshifted) features over its compared points (the centre term)."""
    offset = np.zeros_like(rarity) if offset is None else offset
    norm = (img.astype(np.float64) / 255.0 - np.array(w.mean)) / np.array(w.std)
    W = w.weight.astype(np.float64)
    half = 5
    out = []
    for c in range(len(boxes)):
        x0, y0, bw, bh = boxes[c]
        gx0, gy0, gw, gh = gboxes[c]
        crgb = render_gain * rgb[pix_off[c] : pix_off[c + 1]].reshape(bh, bw, 3).astype(np.float64)
        if render_tone != 1.0:
            crgb = srgb_exposed(crgb, render_tone)
        cmask = mask[pix_off[c] : pix_off[c + 1]].reshape(bh, bw).astype(bool)
        comp = img.astype(np.float64) / 255.0
        if fill:
            comp[:] = np.array(w.mean)
        for yy, xx in zip(*np.nonzero(cmask), strict=True):
            if 0 <= y0 + yy < comp.shape[0] and 0 <= x0 + xx < comp.shape[1]:
                comp[y0 + yy, x0 + xx] = crgb[yy, xx]
        compn = (comp - np.array(w.mean)) / np.array(w.std)
        full = np.zeros((comp.shape[0] + 2 * half, comp.shape[1] + 2 * half), bool)  # the mask, padded by half
        for yy, xx in zip(*np.nonzero(cmask), strict=True):
            if -half <= y0 + yy < comp.shape[0] + half and -half <= x0 + xx < comp.shape[1] + half:
                full[y0 + yy + half, x0 + xx + half] = True

        def compared(gx, gy, x0=x0, y0=y0, bw=bw, bh=bh, cmask=cmask):  # this candidate's box and mask
            u, v = half + stride * gx, half + stride * gy
            inside = x0 <= u < x0 + bw and y0 <= v < y0 + bh
            if not (inside and cmask[v - y0, u - x0]):
                return NOT_ON_MASK
            return None if 0 <= gx < rarity.shape[1] and 0 <= gy < rarity.shape[0] else 0.0

        def feature(arr, gx, gy):
            u, v = half + stride * gx, half + stride * gy
            return (W * arr[v - half : v + half + 1, u - half : u + half + 1].transpose(2, 0, 1)[None]).sum(
                (1, 2, 3)
            ) + w.bias

        if centre:
            cells = [(gx, gy) for gy in range(gy0, gy0 + gh) for gx in range(gx0, gx0 + gw) if compared(gx, gy) is None]
            f_mean = np.mean([feature(compn, gx, gy) for gx, gy in cells], axis=0)
            o_mean = np.mean([feature(norm, gx, gy) for gx, gy in cells], axis=0)
        for gy in range(gy0, gy0 + gh):
            for gx in range(gx0, gx0 + gw):
                u, v = half + stride * gx, half + stride * gy
                skip = compared(gx, gy)
                if skip is not None:
                    out.append(skip)
                    continue
                f = feature(compn, gx, gy)
                if light:
                    f = _lit(W, w, comp[v - half : v + half + 1, u - half : u + half + 1], light)
                hx, hy = gx + shift[0], gy + shift[1]
                if not (0 <= hx < rarity.shape[1] and 0 <= hy < rarity.shape[0]):
                    out.append(0.0)
                    continue
                p, q = half + stride * hx, half + stride * hy
                fo = (W * norm[q - half : q + half + 1, p - half : p + half + 1].transpose(2, 0, 1)[None]).sum(
                    (1, 2, 3)
                )
                fo += w.bias
                if light:
                    fo = _lit(W, w, img[q - half : q + half + 1, p - half : p + half + 1] / 255.0, light)
                if relu:
                    f, fo = np.maximum(f, 0.0), np.maximum(fo, 0.0)
                share = full[v : v + 2 * half + 1, u : u + 2 * half + 1].mean() if weighted else 1.0
                denom = np.linalg.norm(f) * np.linalg.norm(fo)
                cos = f @ fo / denom if denom > 1e-12 else 0.0
                if rectified:
                    fr, gr = np.maximum(f, 0.0), np.maximum(fo, 0.0)
                    denom_r = np.linalg.norm(fr) * np.linalg.norm(gr)
                    cos = (1 - rectified) * cos + rectified * (fr @ gr / denom_r if denom_r > 1e-12 else 0.0)
                if centre:
                    fc, gc = f - f_mean, fo - o_mean
                    denom_c = np.linalg.norm(fc) * np.linalg.norm(gc)
                    cos = (1 - centre) * cos + centre * (fc @ gc / denom_c if denom_c > 1e-12 else 0.0)
                value = cos * share * rarity[hy, hx] - offset[hy, hx]
                if outline > 0:
                    value += outline * _numpy_outline(cmask, x0, y0, u, v, stride, edge, shift)
                out.append(value)
    return np.array(out)


def _lit(W, w: FeatureWeights, window01, gamma, floor=0.1):
    """conv1 of an RGB window in [0, 1] scaled by (ref / max(its mean, floor))^gamma first (the light
    term), ref the preprocessing mean's brightness; then the network's own normalisation, in float64."""
    scale = (np.mean(w.mean) / max(window01.mean(), floor)) ** gamma
    x = (scale * window01 - np.array(w.mean)) / np.array(w.std)
    return (W * x.transpose(2, 0, 1)[None]).sum((1, 2, 3)) + w.bias


def _numpy_outline(cmask, x0, y0, u, v, reach, edge, shift):
    """_numpy_scores' outline credit of on-mask pixel (u, v) (0 off the outline)."""

    def on(x, y):
        return 0 <= x - x0 < cmask.shape[1] and 0 <= y - y0 < cmask.shape[0] and bool(cmask[y - y0, x - x0])

    n = np.zeros(2)
    best = None
    for d in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        t = next((k for k in range(1, reach + 1) if not on(u + k * d[0], v + k * d[1])), None)
        if t is None:
            continue
        n += (reach + 1 - t) / reach * np.array(d, float)
        if best is None or t < best[0]:
            best = (t, u + t * d[0], v + t * d[1])
    if best is None or np.linalg.norm(n) < 1e-6:
        return 0.0
    bx, by = best[1] + shift[0] * reach, best[2] + shift[1] * reach
    if not (0 <= bx < edge.shape[1] and 0 <= by < edge.shape[0]):
        return 0.0
    return abs(edge[by, bx].astype(np.float64) @ n) / np.linalg.norm(n)


def _random_batch(rng, H, W_, stride):
    """A photo and five rendered boxes (two hanging over the image's edges) with random colours and masks."""
    img = rng.integers(0, 256, (H, W_, 3), dtype=np.uint8)
    boxes = np.array([[4, 6, 20, 15], [30, 0, 22, 40], [0, 25, 10, 15], [40, -9, 20, 18], [-7, 30, 15, 14]], np.int32)
    sizes = boxes[:, 2] * boxes[:, 3]
    pix_off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32)
    rgb = rng.random((pix_off[-1], 3)).astype(np.float32)
    mask = (rng.random(pix_off[-1]) < 0.7).astype(np.uint8)
    batch = RenderedBatch(
        wp.array(rgb, dtype=wp.vec3, device=DEVICE),
        wp.array(mask, dtype=wp.uint8, device=DEVICE),
        wp.array(boxes, dtype=wp.vec4i, device=DEVICE),
        wp.array(pix_off, dtype=wp.int32, device=DEVICE),
        len(boxes),
    )
    return img, boxes, pix_off, rgb, mask, batch


def _case(seed: int, sc: FeatureScorer, H: int = 40, W_: int = 52):
    """_random_batch's photo and boxes with random rarity, and the photo's features, norms and maps on the
    device for scorer sc."""
    rng = np.random.default_rng(seed)
    img, boxes, pix_off, rgb, mask, batch = _random_batch(rng, H, W_, sc.stride)
    rows, cols = grid_shape(W_, H, 11, sc.stride)
    gboxes = grid_boxes(boxes, 11, sc.stride)
    rarity = rng.random((rows, cols)).astype(np.float32)
    image = sc.image_to_device(img)
    obs = sc.observed_features(image)
    norms = wp.array(np.linalg.norm(obs.numpy().astype(np.float64), axis=-1).astype(np.float32), device=DEVICE)
    pw = point_weights(wp.array(rarity, device=DEVICE))
    return img, boxes, pix_off, rgb, mask, batch, gboxes, rarity, image, obs, norms, pw


@pytest.mark.parametrize("conv", ["warp", "torch"])
def test_shifted_scores_equal_numpy_reference(random_weights, conv):
    """score_terms' shift: block s of kernel #2's values compares every point with the photo's feature
    shifts[s] grid cells away (both conv forms), and the first block is the unshifted values."""
    stride = 3
    sc = FeatureScorer(random_weights, DEVICE, stride, conv=conv)
    img, boxes, pix_off, rgb, mask, batch, gboxes, rarity, image, obs, norms, pw = _case(5, sc)
    shifts = shift_array(1, DEVICE)
    assert sorted(map(tuple, shifts.numpy().tolist())) == [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
    vals, pt_off = sc.score_points(image, batch, gboxes, obs, norms, pw, shifts)
    plain, _ = sc.score_points(image, batch, gboxes, obs, norms, pw)
    n = int(pt_off.numpy()[-1])
    got = vals.numpy().reshape(9, n)
    assert np.array_equal(got[0], plain.numpy())  # (0, 0) first: the plain score's values
    for s, d in enumerate(shifts.numpy().tolist()):
        ref = _numpy_scores(img, rgb, mask, pix_off, boxes, gboxes, random_weights, stride, rarity, shift=tuple(d))
        off = ref == NOT_ON_MASK
        assert np.array_equal(got[s] == NOT_ON_MASK, off)
        assert np.abs(got[s][~off] - ref[~off]).max() < 1e-4, d


@pytest.mark.parametrize("conv", ["warp", "torch"])
@pytest.mark.parametrize("surround,relu", [("photo", False), ("fill", False), ("photo", True)])
def test_exposure_scores_equal_numpy_reference(random_weights, conv, surround, relu):
    """score_terms' exposure: block k S + s of kernel #2's values is the render read gains[k] times as bright,
    compared shifts[s] cells away (both conv forms; onto the photo or the fill; raw or rectified conv1)."""
    stride = 3
    sc = FeatureScorer(random_weights, DEVICE, stride, relu=relu, conv=conv, surround=surround)
    img, boxes, pix_off, rgb, mask, batch, gboxes, rarity, image, obs, norms, pw = _case(11, sc)
    shifts, gains = shift_array(1, DEVICE), exposure_array(1.0, DEVICE)
    assert np.allclose(gains.numpy(), [1, 2**-0.5, 2**0.5, 0.5, 2])
    vals, pt_off = sc.score_points(image, batch, gboxes, obs, norms, pw, shifts, gains)
    n = int(pt_off.numpy()[-1])
    got = vals.numpy().reshape(5, 9, n)
    for k, g in enumerate(gains.numpy().tolist()):
        for s, d in enumerate(shifts.numpy().tolist()):
            ref = _numpy_scores(
                img, rgb, mask, pix_off, boxes, gboxes, random_weights, stride, rarity,
                fill=surround == "fill", shift=tuple(d), relu=relu, render_gain=g,
            )  # fmt: skip
            off = ref == NOT_ON_MASK
            assert np.array_equal(got[k, s] == NOT_ON_MASK, off)
            assert np.abs(got[k, s][~off] - ref[~off]).max() < 1e-4, (g, d)


@pytest.mark.parametrize("conv", ["warp", "torch"])
@pytest.mark.parametrize("surround", ["photo", "fill"])
def test_tone_scores_equal_numpy_reference(random_weights, conv, surround):
    """score_terms' tone: block j S + s of kernel #2's values is the render read at exposure tone[j] with
    its highlights clipped at white, compared shifts[s] cells away (both conv forms, onto the photo or
    the fill); exposure 1 first, the plain score's values bit for bit."""
    stride = 3
    sc = FeatureScorer(random_weights, DEVICE, stride, conv=conv, surround=surround)
    img, boxes, pix_off, rgb, mask, batch, gboxes, rarity, image, obs, norms, pw = _case(13, sc)
    shifts, tone = shift_array(1, DEVICE), tone_gains(2)
    assert np.array_equal(tone, [1, 2, 4])
    # the clipping is there to test: at 4x, a third of the random colours' channels burn out
    assert 0.2 < (srgb_exposed(rgb.astype(np.float64), 4.0) > 1.0 - 1e-9).mean() < 0.6
    vals, pt_off = sc.score_points(image, batch, gboxes, obs, norms, pw, shifts, None, tone)
    plain, _ = sc.score_points(image, batch, gboxes, obs, norms, pw, shifts)
    n = int(pt_off.numpy()[-1])
    got = vals.numpy().reshape(3, 9, n)
    assert np.array_equal(got[0], plain.numpy().reshape(9, n))
    for j, t in enumerate(tone.tolist()):
        for s, d in enumerate(shifts.numpy().tolist()):
            ref = _numpy_scores(
                img, rgb, mask, pix_off, boxes, gboxes, random_weights, stride, rarity,
                fill=surround == "fill", shift=tuple(d), render_tone=t,
            )  # fmt: skip
            off = ref == NOT_ON_MASK
            assert np.array_equal(got[j, s] == NOT_ON_MASK, off)
            assert np.abs(got[j, s][~off] - ref[~off]).max() < 1e-4, (t, d)


def test_tone_refuses_exposure_and_light(random_weights):
    sc = FeatureScorer(random_weights, DEVICE, 3)
    img, boxes, pix_off, rgb, mask, batch, gboxes, rarity, image, obs, norms, pw = _case(13, sc)
    with pytest.raises(PerchError, match="tone term"):
        sc.score_points(image, batch, gboxes, obs, norms, pw, None, exposure_array(1.0, DEVICE), tone_gains(1))


def test_exposure_gains_are_half_stops():
    assert np.array_equal(exposure_gains(0.0), [1.0])
    assert np.allclose(exposure_gains(0.5), [1, 2**-0.5, 2**0.5])
    got = exposure_gains(2.0)
    assert got[0] == 1.0 and len(got) == 9 and np.isclose(got.min(), 0.25) and np.isclose(got.max(), 4.0)


@pytest.mark.parametrize("conv", ["warp", "torch"])
def test_outline_term_equals_numpy_reference(random_weights, conv):
    """score_terms' outline: a point on the candidate's outline also earns w |e . n| from the photo's edge
    map at its nearest off-mask pixel, under every shift (both conv forms); points off the outline and
    w = 0 are unchanged."""
    rng = np.random.default_rng(7)
    H, W_, stride = 40, 52, 3
    img, boxes, pix_off, rgb, mask, batch = _random_batch(rng, H, W_, stride)
    # Solid blobs, not noise: outlines with interiors, so that both kinds of point are exercised.
    for c in range(len(boxes)):
        bw, bh = int(boxes[c, 2]), int(boxes[c, 3])
        yy, xx = np.mgrid[0:bh, 0:bw]
        blob = ((xx - bw / 2) / (0.45 * bw)) ** 2 + ((yy - bh / 2) / (0.45 * bh)) ** 2 < 1
        mask[pix_off[c] : pix_off[c + 1]] = blob.reshape(-1)
    batch = RenderedBatch(batch.rgb, wp.array(mask, dtype=wp.uint8, device=DEVICE), batch.box, batch.pix_off, batch.n)
    rows, cols = grid_shape(W_, H, 11, stride)
    gboxes = grid_boxes(boxes, 11, stride)
    rarity = rng.random((rows, cols)).astype(np.float32)
    edge = edge_map(img)
    assert np.linalg.norm(edge, axis=-1).max() < 1.0
    sc = FeatureScorer(random_weights, DEVICE, stride, conv=conv)
    image = sc.image_to_device(img)
    obs = sc.observed_features(image)
    norms = wp.array(np.linalg.norm(obs.numpy().astype(np.float64), axis=-1).astype(np.float32), device=DEVICE)
    gain = wp.array(rarity, device=DEVICE)
    w = 0.4
    pw = point_weights(gain, None, wp.array(edge, dtype=wp.vec2, device=DEVICE), w)
    shifts = shift_array(1, DEVICE)
    vals, pt_off = sc.score_points(image, batch, gboxes, obs, norms, pw, shifts)
    plain, _ = sc.score_points(image, batch, gboxes, obs, norms, point_weights(gain))
    n = int(pt_off.numpy()[-1])
    got = vals.numpy().reshape(len(shifts.numpy()), n)
    gained = 0
    for s, d in enumerate(shifts.numpy().tolist()):
        ref = _numpy_scores(
            img, rgb, mask, pix_off, boxes, gboxes, random_weights, stride, rarity, shift=tuple(d), outline=w, edge=edge
        )
        off = ref == NOT_ON_MASK
        assert np.array_equal(got[s] == NOT_ON_MASK, off)
        assert np.abs(got[s][~off] - ref[~off]).max() < 1e-4, d
        if d == [0, 0]:
            gained = int((got[s][~off] > plain.numpy()[~off] + 1e-6).sum())
            assert np.all(got[s][~off] >= plain.numpy()[~off] - 1e-6)  # the term only adds
    assert 10 < gained < int((~(plain.numpy() == NOT_ON_MASK)).sum())  # outline points gain, interior ones do not


def test_edge_map_is_normalised_and_contrast_invariant():
    """outline.edge_map: a vertical step edge gives a gradient along +x there, below 1 in length, the same
    for a photo of half the contrast; a flat photo gives zeros; edge_ceiling bounds |e| within a stride."""
    img = np.full((30, 40, 3), 40, np.uint8)
    img[:, 20:] = 200
    e = edge_map(img)
    mag = np.linalg.norm(e, axis=-1)
    assert mag.max() < 1.0 and mag[15, 19] > 0.5 and e[15, 19, 0] > 0 and abs(e[15, 19, 1]) < 1e-6
    assert mag[15, 5] < 1e-3
    half_contrast = (120 + (img.astype(int) - 120) // 2).astype(np.uint8)
    assert np.allclose(edge_map(half_contrast), e, atol=1e-6)
    assert not edge_map(np.full((20, 20, 3), 90, np.uint8)).any()
    rows, cols = grid_shape(40, 30, 11, 3)
    ceil = edge_ceiling(e, rows, cols, 11, 3)
    for gy in range(rows):
        for gx in range(cols):
            u, v = 5 + 3 * gx, 5 + 3 * gy
            assert ceil[gy, gx] >= mag[max(0, v - 3) : v + 4, max(0, u - 3) : u + 4].max()


def test_best_over_shifts_reduces_each_shift_block_as_a_candidate():
    """top_alpha_mean_device over S blocks + best_over_shifts = max over s of the NumPy top-α mean."""
    rng = np.random.default_rng(2)
    counts = np.array([5, 0, 9, 3])
    pt_off = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    S, n = 4, int(pt_off[-1])
    vals = rng.random(S * n).astype(np.float32)
    vals[rng.random(S * n) < 0.2] = NOT_ON_MASK
    off = wp.array(pt_off, dtype=wp.int32, device=DEVICE)
    scores, _ = top_alpha_mean_device(wp.array(vals, dtype=float, device=DEVICE), off, 0.5, blocks=S)
    got = best_over_shifts(scores.numpy(), S)
    ref = np.max([top_alpha_mean(vals[s * n : (s + 1) * n], pt_off, 0.5)[0] for s in range(S)], axis=0)
    assert np.array_equal(np.isfinite(got), np.isfinite(ref))
    assert np.allclose(got[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=0, atol=1e-12)


@pytest.mark.parametrize("features", ["raw", "relu", "blend"])
@pytest.mark.parametrize("surround", ["photo", "fill", "weighted"])
@pytest.mark.parametrize("conv", ["warp", "torch"])
def test_candidate_scores_equal_numpy_reference(random_weights, conv, surround, features):
    """Both conv forms, windows composited onto the photo (thesis) or onto the fill, with an offset map
    (score_terms' background term) or none, raw conv1, rectified (`--relu`) or both blended (the
    `rectified` term, b = 0.4)."""
    relu, rectified = features == "relu", 0.4 if features == "blend" else 0.0
    rng = np.random.default_rng(3)
    H, W_, stride = 40, 52, 3
    # The last two boxes hang over the image's edges: their outside points count as 0.
    img, boxes, pix_off, rgb, mask, batch = _random_batch(rng, H, W_, stride)
    rows, cols = grid_shape(W_, H, 11, stride)
    gboxes = grid_boxes(boxes, 11, stride)
    rarity = rng.random((rows, cols)).astype(np.float32)
    offset = (0.3 * rng.random((rows, cols)) * rarity).astype(np.float32) if surround == "fill" else None

    sc = FeatureScorer(random_weights, DEVICE, stride, relu=relu, conv=conv, surround=surround)
    image = sc.image_to_device(img)
    obs = sc.observed_features(image)
    norms = np.linalg.norm(obs.numpy().astype(np.float64), axis=-1).astype(np.float32)
    pw = point_weights(
        wp.array(rarity, device=DEVICE),
        None if offset is None else wp.array(offset, device=DEVICE),
        rectified=rectified,
    )
    vals, pt_off = sc.score_points(image, batch, gboxes, obs, wp.array(norms, device=DEVICE), pw)
    got = vals.numpy()
    ref = _numpy_scores(
        img,
        rgb,
        mask,
        pix_off,
        boxes,
        gboxes,
        random_weights,
        stride,
        rarity,
        offset,
        surround == "fill",
        surround == "weighted",
        relu=relu,
        rectified=rectified,
    )
    assert got.shape == ref.shape and pt_off.numpy()[-1] == len(ref)
    off = ref == NOT_ON_MASK
    assert np.array_equal(got == NOT_ON_MASK, off) and 0 < off.sum() < len(ref)
    assert (ref == 0.0).sum() > 5  # on-mask points beyond the feature grid were exercised
    assert np.abs(got[~off] - ref[~off]).max() < 1e-4


def test_grid_boxes_hold_exactly_the_centres_inside():
    rng = np.random.default_rng(4)
    stride = 4
    for _ in range(50):
        x0, y0 = rng.integers(-30, 120, 2)
        w, h = rng.integers(1, 40, 2)
        g = grid_boxes(np.array([[x0, y0, w, h]]), 11, stride)[0]
        want = [
            (gx, gy)
            for gy in range(-20, 60)
            for gx in range(-20, 60)
            if x0 <= 5 + stride * gx < x0 + w and y0 <= 5 + stride * gy < y0 + h
        ]
        got = [(gx, gy) for gy in range(g[1], g[1] + g[3]) for gx in range(g[0], g[0] + g[2])]
        assert sorted(got) == sorted(want)


def test_folded_weights_act_on_unit_rgb():
    rng = np.random.default_rng(5)
    w = FeatureWeights(
        rng.normal(size=(4, 3, 3, 3)).astype(np.float32),
        rng.normal(size=4).astype(np.float32),
        *PREPROCESSING["torchvision"],
        "t",
    )
    Wt, b = w.folded()
    x = rng.random((3, 3, 3))  # (y, x, ch) in [0, 1]
    ref = (w.weight * ((x - np.array(w.mean)) / np.array(w.std)).transpose(2, 0, 1)[None]).sum((1, 2, 3)) + w.bias
    assert np.allclose(x.reshape(-1) @ Wt + b, ref, atol=1e-4)


def test_npz_without_preprocessing_is_refused(tmp_path):
    p = tmp_path / "w.npz"
    np.savez(p, weight=np.zeros((2, 3, 3, 3), np.float32), bias=np.zeros(2, np.float32))
    with pytest.raises(PerchError, match="preprocessing"):
        load_npz(p)
    np.savez(p, weight=np.zeros((2, 3, 3, 3), np.float32))
    with pytest.raises(PerchError, match="'bias'"):
        load_npz(p)
    np.savez(p, weight=np.zeros((2, 3, 4, 4), np.float32), bias=np.zeros(2, np.float32), preprocessing="caffe")
    with pytest.raises(PerchError, match="odd k"):
        load_npz(p)


@pytest.mark.parametrize("conv", ["warp", "torch"])
@pytest.mark.parametrize("gamma", [0.5, 1.0])
def test_light_scores_equal_numpy_reference(random_weights, conv, gamma):
    """score_terms' light: every window, the photo's and the composited candidate's, scaled towards the
    preprocessing mean's brightness before conv1 (both conv forms), against a float64 reference."""
    rng = np.random.default_rng(8)
    H, W_, stride = 40, 52, 3
    img, boxes, pix_off, rgb, mask, batch = _random_batch(rng, H, W_, stride)
    img[:, :20] //= 8  # a dark part, below the floor
    rows, cols = grid_shape(W_, H, 11, stride)
    gboxes = grid_boxes(boxes, 11, stride)
    rarity = rng.random((rows, cols)).astype(np.float32)
    sc = FeatureScorer(random_weights, DEVICE, stride, conv=conv, light=gamma)
    image = sc.image_to_device(img)
    obs = sc.observed_features(image)
    norms = wp.array(np.linalg.norm(obs.numpy().astype(np.float64), axis=-1).astype(np.float32), device=DEVICE)
    vals, _ = sc.score_points(image, batch, gboxes, obs, norms, point_weights(wp.array(rarity, device=DEVICE)))
    ref = _numpy_scores(img, rgb, mask, pix_off, boxes, gboxes, random_weights, stride, rarity, light=gamma)
    got = vals.numpy()
    off = ref == NOT_ON_MASK
    assert np.array_equal(got == NOT_ON_MASK, off) and (~off).sum() > 50
    np.testing.assert_allclose(got[~off], ref[~off], atol=2e-4)
    plain = FeatureScorer(random_weights, DEVICE, stride, conv=conv)
    unlit, _ = plain.score_points(
        image, batch, gboxes, plain.observed_features(image), norms, point_weights(wp.array(rarity, device=DEVICE))
    )
    assert np.abs(unlit.numpy()[~off] - got[~off]).max() > 0.05  # the term changes the scores


def test_light_makes_photo_features_brightness_invariant(random_weights):
    """With light 1 a window's feature does not depend on a brightness factor (above the floor), so a
    photo at half its brightness has the same features; without it they point elsewhere."""
    img = np.random.default_rng(9).integers(60, 128, (30, 34, 3)).astype(np.uint8) * 2  # even: halves exactly
    lit = FeatureScorer(random_weights, DEVICE, 4, light=1.0)
    a = lit.observed_features(lit.image_to_device(img)).numpy().astype(np.float64)
    b = lit.observed_features(lit.image_to_device(img // 2)).numpy().astype(np.float64)
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-3 * np.abs(a).max())
    plain = FeatureScorer(random_weights, DEVICE, 4)
    c = plain.observed_features(plain.image_to_device(img)).numpy().astype(np.float64).reshape(-1, 96)
    d = plain.observed_features(plain.image_to_device(img // 2)).numpy().astype(np.float64).reshape(-1, 96)
    cos = (c * d).sum(1) / np.linalg.norm(c, axis=1) / np.linalg.norm(d, axis=1)
    assert cos.min() < 0.99


@pytest.mark.parametrize("surround,shift", [("photo", (0, 0)), ("fill", (1, -1)), ("weighted", (0, 1))])
def test_centre_scores_equal_numpy_reference(random_weights, surround, shift):
    """score_terms' centre (c = 0.6): kernel #2's torch form blends in the cosine of the candidate's
    features and the photo's, each less its mean over the candidate's compared points (the undisplaced
    ones, whatever the shift); the Warp form, which keeps no features, refuses it."""
    stride = 3
    sc = FeatureScorer(random_weights, DEVICE, stride, conv="torch", surround=surround)
    img, boxes, pix_off, rgb, mask, batch, gboxes, rarity, image, obs, norms, _ = _case(7, sc)
    pw = point_weights(wp.array(rarity, device=DEVICE), centre=0.6)
    shifts = shift_array(1, DEVICE)
    vals, pt_off = sc.score_points(image, batch, gboxes, obs, norms, pw, shifts)
    got = vals.numpy().reshape(9, int(pt_off.numpy()[-1]))[[tuple(d) for d in shifts.numpy().tolist()].index(shift)]
    kw = dict(fill=surround == "fill", weighted=surround == "weighted", shift=shift)
    ref = _numpy_scores(img, rgb, mask, pix_off, boxes, gboxes, random_weights, stride, rarity, centre=0.6, **kw)
    off = ref == NOT_ON_MASK
    assert np.array_equal(got == NOT_ON_MASK, off) and 0 < off.sum() < len(ref)
    assert np.abs(got[~off] - ref[~off]).max() < 1e-4
    plain = _numpy_scores(img, rgb, mask, pix_off, boxes, gboxes, random_weights, stride, rarity, **kw)
    assert np.abs(plain[~off] - ref[~off]).max() > 0.01  # the term changes the values
    warp_sc = FeatureScorer(random_weights, DEVICE, stride, conv="warp", surround=surround)
    img, boxes, pix_off, rgb, mask, batch, gboxes, rarity, image, obs, norms, _ = _case(7, warp_sc)
    with pytest.raises(PerchError, match="centre term needs"):
        warp_sc.score_points(image, batch, gboxes, obs, norms, pw)
