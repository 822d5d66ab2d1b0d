"""Scoring: photo features (kernel #2, once per photo), candidate scores (kernel #2 per batch), top-α mean."""

from __future__ import annotations

import contextlib
import math
import queue

import numpy as np
import warp as wp

from .errors import PerchError
from .features import FeatureWeights
from .kernels.features import (
    NOT_ON_MASK,
    Exposure,
    PointLayout,
    PointWeights,
    Surround,
    composite_crops,
    feature_kernels,
    read_at_exposure,
    sums_to_means,
)
from .kernels.hidden import HIDDEN
from .kernels.reduce import top_alpha_mean as top_alpha_mean_kernel
from .kernels.render import RenderedBoxes
from .render import RenderedBatch, flat_offsets, point_layout
from .score_terms import SURROUNDS, exposure_gains


def grid_shape(width: int, height: int, kernel_size: int, stride: int) -> tuple[int, int]:
    """(rows, cols) of the feature grid: an unpadded stride-s convolution of a width x height image."""
    return (height - kernel_size) // stride + 1, (width - kernel_size) // stride + 1


# How kernel #2 convolves a candidate's windows: "warp" (in the kernel, point by point), "torch"
# (torch's conv2d on each candidate's composited crop), or "auto": torch on the CPU, where it is
# measured faster (docs/performance.md, "Conv1 through torch"); warp on a GPU, where it is not measured.
CONVS = ("auto", "warp", "torch")
# The light term's floor: a window darker than this mean brightness (RGB in [0, 1]) is brightened as if it
# were this bright, so that the sensor noise of a black patch is not magnified without limit.
LIGHT_FLOOR = 0.1


def auto_conv(device: str, centre: float = 0.0) -> str:
    """What conv "auto" runs on this device for a score with this centre term: torch on the CPU (measured
    faster there), warp on a GPU unless the score centres each candidate's features, which only the
    torch form keeps (score_terms: centre)."""
    return "torch" if wp.get_device(device).is_cpu or centre > 0.0 else "warp"


@contextlib.contextmanager
def torch_threads(n: int):
    """torch's intra-op threads set to n for the block, then restored. The engine scores batches on its
    own threads; each batch's conv2d calls then run on that batch's thread alone."""
    # torch is imported where the torch form runs, here and below: a GPU search (conv "warp") never
    # needs it, and it takes seconds to import.
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def cudnn_full_precision():
    """cuDNN convolutions in IEEE fp32, deterministic, for the block, then restored. By default torch
    lets cuDNN convolve fp32 in TF32 (10-bit mantissa) on Ampere and later GPUs, which would put the
    candidates' features about 1e-3 off the photo's (kernel #2's Warp form, full fp32) and off the
    CPU's; and it may pick an algorithm whose sums depend on the run."""
    import inspect

    import torch

    flags = {"enabled": True, "benchmark": False, "deterministic": True, "allow_tf32": False}
    if "fp32_precision" in inspect.signature(torch.backends.cudnn.flags).parameters:  # torch >= 2.9
        flags["fp32_precision"] = "ieee"
    return torch.backends.cudnn.flags(**flags)


class FeatureScorer:
    """Conv1 weights on a device, and the kernels specialised for their channel count."""

    def __init__(
        self,
        weights: FeatureWeights,
        device: str,
        stride: int,
        relu: bool = False,
        conv: str = "warp",
        surround: str = "photo",
        light: float = 0.0,
    ):
        if conv not in ("warp", "torch"):
            raise PerchError(f"conv must be warp or torch, got {conv!r}")
        if surround not in SURROUNDS:
            raise PerchError(f"surround must be one of {', '.join(SURROUNDS)}, got {surround!r}")
        self.device = device
        self.conv = conv
        self.ks = weights.kernel_size
        self.stride = int(stride)
        self.relu = int(bool(relu))
        kernels = feature_kernels(weights.channels)
        self.vecC, self.k_observed, self.k_score, self.k_score_features, self.k_sums = kernels
        Wt, b = weights.folded()
        self.folded_bias = b  # conv1's bias on RGB in [0, 1] (the score term cluster=direction removes it)
        with wp.ScopedDevice(device):
            self.Wt = wp.array(Wt, dtype=self.vecC)
            self.bias = self.vecC(*b.tolist())
            self._dummy_rgb = wp.zeros(1, dtype=wp.vec3)
            self._dummy_mask = wp.zeros(1, dtype=wp.uint8)
            self._dummy_feat = wp.zeros(1, dtype=float)
        self._shifts: dict[int, wp.array] = {0: shift_array(0, device)}
        self._gains: dict[float, wp.array] = {0.0: exposure_array(0.0, device)}
        # Beyond the mask a window sees the photo, or the preprocessing mean (conv1's zero input);
        # "weighted": the photo, with the cosine weighted by the window's covered fraction.
        self.surround = Surround()
        self.surround.use_fill = int(surround == "fill")
        self.surround.fill = wp.vec3(*(float(m) for m in weights.mean))
        self.surround.by_fraction = int(surround == "weighted")
        # The light term (perch_warp.score_terms): every window, the photo's and the candidates', brought
        # towards the preprocessing mean's brightness before conv1.
        self.exposure = Exposure()
        self.exposure.gamma = float(light)
        self.exposure.ref = float(np.mean(weights.mean))
        self.exposure.floor = LIGHT_FLOOR
        self._buffers: queue.SimpleQueue = queue.SimpleQueue()  # free buffer sets of the torch form
        if conv == "torch":
            import torch

            C, ks = weights.channels, self.ks
            # The folded weights back in OIHW: Wt's rows are (dy, dx, ch_in).
            oihw = Wt.reshape(ks, ks, 3, C).transpose(3, 2, 0, 1)
            tdev = wp.device_to_torch(device)
            self._t_weight = torch.from_numpy(np.ascontiguousarray(oihw)).to(tdev)
            self._t_bias = torch.from_numpy(b).to(tdev)

    def shifts(self, radius: int) -> wp.array:
        """shift_array(radius) on this scorer's device, made once per radius."""
        if radius not in self._shifts:
            self._shifts[radius] = shift_array(radius, self.device)
        return self._shifts[radius]

    def gains(self, stops: float) -> wp.array:
        """exposure_array(stops) on this scorer's device, made once per value."""
        if stops not in self._gains:
            self._gains[stops] = exposure_array(stops, self.device)
        return self._gains[stops]

    @contextlib.contextmanager
    def conv_settings(self):
        """torch's settings while batches are scored, for the torch form: one thread per calling
        thread (the engine already runs one batch per core, and a candidate's features must not depend
        on a thread count) and, on a GPU, cuDNN in full fp32 (cudnn_full_precision). Global state, so
        entered once around all of a search's batches, not per batch; nothing for the Warp form."""
        with contextlib.ExitStack() as stack:
            if self.conv == "torch":
                stack.enter_context(torch_threads(1))
                if not wp.get_device(self.device).is_cpu:
                    stack.enter_context(cudnn_full_precision())
            yield

    def warm_up(self) -> None:
        """Build both kernels now (a tiny launch each) so that compile time is not billed to a search stage."""
        ks = self.ks
        image = wp.zeros((ks, ks), dtype=wp.vec3, device=self.device)
        obs = self.observed_features(image)
        with wp.ScopedDevice(self.device):
            one = point_weights(wp.zeros((1, 1), dtype=float))
            batch = RenderedBatch(
                wp.zeros(1, dtype=wp.vec3),
                wp.zeros(1, dtype=wp.uint8),
                wp.array(np.array([[0, 0, 1, 1]], np.int32), dtype=wp.vec4i),
                wp.array(np.array([0, 1], np.int32), dtype=wp.int32),
                1,
            )
        self.score_points(image, batch, np.array([[0, 0, 1, 1]], np.int32), obs, one.gain, one)
        wp.synchronize_device(self.device)

    def image_to_device(self, image_rgb: np.ndarray) -> wp.array:
        return wp.array(np.asarray(image_rgb, dtype=np.float32) / 255.0, dtype=wp.vec3, device=self.device)

    def observed_features(self, image: wp.array) -> wp.array:
        """Feature map (rows, cols) of C-vectors of the photo (device array)."""
        rows, cols = grid_shape(image.shape[1], image.shape[0], self.ks, self.stride)
        with wp.ScopedDevice(self.device):
            out = wp.empty((rows, cols), dtype=self.vecC)
            wp.launch(
                self.k_observed,
                dim=(rows, cols),
                inputs=[
                    image,
                    self.Wt,
                    self.bias,
                    self.ks,
                    self.stride,
                    self.relu,
                    self.exposure,
                    self._dummy_rgb,
                    self._dummy_mask,
                ],
                outputs=[out],
            )
        return out

    def score_points(
        self,
        image: wp.array,
        batch: RenderedBatch,
        gboxes: np.ndarray,
        obs_feat: wp.array,
        obs_norm: wp.array,
        pw: PointWeights,
        shifts: wp.array | None = None,
        gains: wp.array | None = None,
        tone: np.ndarray | None = None,
    ) -> tuple[wp.array, wp.array]:
        """similarity x gain - offset (pw: the photo's maps, `point_weights`) at every feature-grid
        point of each candidate's box and the flat
        offsets (B + 1,) int32 of each candidate's points, both device arrays (they stay there
        for `top_alpha_mean_device`); off-mask points hold NOT_ON_MASK. With `shifts` (shift_array,
        S of them; default: none) the values are S such blocks, block s comparing each point with the
        photo's feature shifts[s] grid cells away (kernels/features.py). With `gains` (exposure_array,
        G of them; default: none) the render is read at each gain in turn: G S blocks, block k S + s
        that of gain k and shift s. With `tone` (score_terms.tone_gains, host floats, 1 first; T of
        them) the rendered colours are read at each exposure, clipped at white (read_at_exposure):
        T times those blocks, exposure j's from j G S on."""
        pts = point_layout(batch.box, gboxes, self.ks, self.stride, self.device)
        shifts = self.shifts(0) if shifts is None else shifts
        gains = self.gains(0.0) if gains is None else gains
        tone = np.ones(1, np.float32) if tone is None else np.asarray(tone, np.float32)
        exposed = gains.shape[0] > 1
        if exposed and self.exposure.gamma != 0.0:
            raise PerchError("the exposure term cannot be combined with the light term")
        if len(tone) > 1 and (exposed or self.exposure.gamma != 0.0):
            raise PerchError("the tone term cannot be combined with the exposure or light term")
        n_blocks = pts.n_points * shifts.shape[0] * gains.shape[0]
        # what every point is compared with, and how
        compare = [self.surround, obs_feat, obs_norm, pw, shifts, gains]
        with wp.ScopedDevice(self.device):
            out = wp.empty(n_blocks * len(tone), dtype=float)
            for j, g in enumerate(tone.tolist()):
                seen = batch.as_struct()
                if g != 1.0:  # the render as it is for 1: the plain score's arithmetic, bit for bit
                    seen.rgb = wp.empty_like(batch.rgb)
                    wp.launch(read_at_exposure, dim=batch.rgb.shape[0], inputs=[batch.rgb, g], outputs=[seen.rgb])
                self._score_into(image, seen, gboxes, pts, compare, exposed, out[j * n_blocks : (j + 1) * n_blocks])
        return out, pts.pt_off

    def _score_into(
        self,
        image: wp.array,
        seen: RenderedBoxes,
        gboxes: np.ndarray,
        pts: PointLayout,
        compare: list,
        exposed: bool,
        out: wp.array,
    ) -> None:
        """score_points' blocks for one reading of the render (seen), into out; `compare`: what every
        point is compared with, and how (kernel #2's trailing inputs); `exposed`: with the exposure
        term's gains (conv1's response split in two)."""
        centre = compare[3].centre > 0.0
        if centre and (exposed or self.relu or self.conv != "torch"):
            raise PerchError("the centre term needs conv1's raw features kept per point: --conv torch, no --relu, "
                             "no exposure term")  # fmt: skip
        if self.conv == "torch":
            bufs = self._take_buffers()
            try:
                if exposed:  # conv1 is linear: the rendered pixels' response apart from the rest's
                    feat = self._torch_features(image, seen, gboxes, bufs, part=1)
                    rest = self._torch_features(image, seen, gboxes, bufs, part=2)
                else:
                    feat = self._torch_features(image, seen, gboxes, bufs)
                    rest = self._dummy_feat
                means = self._dummy_feat
                if centre:  # each candidate's mean features first, then the blended cosines
                    C = int(self._t_weight.shape[0])
                    means = wp.zeros(2 * C * len(gboxes), dtype=float, device=self.device)
                    counts = wp.zeros(len(gboxes), dtype=float, device=self.device)
                    args = [feat, seen, pts, compare[1]]
                    wp.launch(self.k_sums, dim=pts.n_points, inputs=args, outputs=[means, counts])
                    wp.launch(sums_to_means, dim=len(means), inputs=[counts, 2 * C], outputs=[means])
                wp.launch(
                    self.k_score_features,
                    dim=pts.n_points,
                    inputs=[feat, seen, pts, self.relu, *compare, rest, means],
                    outputs=[out],
                )
            finally:
                self._buffers.put(bufs)  # the same stream reads it before a later batch writes it
        else:
            wp.launch(
                self.k_score,
                dim=pts.n_points,
                inputs=[image, seen, pts, self.Wt, self.bias, self.relu, self.exposure, *compare],
                outputs=[out],
            )

    def _torch_features(
        self, image: wp.array, seen: RenderedBoxes, gboxes: np.ndarray, bufs: dict, part: int = 0
    ) -> wp.array:
        """conv1 at every feature point of the batch (seen: kernel #1's output, gboxes: the candidates'
        grid boxes), for `score_features`: candidate c's C planes of its points from C pt_off[c]
        (flat_offsets(gboxes)), a flat device array. Each candidate's windows are composited into
        one crop (composite_crops) that torch's conv2d convolves, one candidate per call, so that a
        candidate's features never depend on the batch it is in. `part` (composite_crops'): 0 the
        composited windows; 1 their rendered pixels alone, without the bias; 2 the rest, with it."""
        import torch

        pt_off = flat_offsets(np.asarray(gboxes, dtype=np.int32))
        crops = crop_boxes(gboxes, self.ks, self.stride)
        crop_off = flat_offsets(crops)
        C = int(self._t_weight.shape[0])
        feat = _grown(bufs, f"feat{part}", C * int(pt_off[-1]), self.device)
        flat = _grown(bufs, "crop", 3 * int(crop_off[-1]), self.device)
        bias = None if part == 1 else self._t_bias
        wp.launch(
            composite_crops,
            dim=(len(crops), int(crops[:, 3].max(initial=0))),
            inputs=[
                image,
                seen,
                wp.array(crops, dtype=wp.vec4i),
                wp.array(crop_off, dtype=wp.int32),
                self.surround,
                part,
            ],
            outputs=[flat],
        )
        f_t, flat_t = wp.to_torch(feat), wp.to_torch(flat)
        on_gpu = not wp.get_device(self.device).is_cpu
        if on_gpu:  # torch runs on its own stream: the crops must be written before it reads them
            wp.synchronize_device(self.device)
        for c in np.flatnonzero(crops[:, 2] * crops[:, 3] > 0):
            w, h = int(crops[c, 2]), int(crops[c, 3])
            x = flat_t[3 * int(crop_off[c]) : 3 * int(crop_off[c + 1])].view(1, 3, h, w)
            y = torch.nn.functional.conv2d(x, self._t_weight, bias, stride=self.stride)
            if self.exposure.gamma != 0.0:  # conv_at's exposure: the unbiased response scaled per window
                lum = torch.nn.functional.avg_pool2d(x.mean(dim=1, keepdim=True), self.ks, stride=self.stride)
                gain = (self.exposure.ref / lum.clamp(min=self.exposure.floor)) ** self.exposure.gamma
                b = self._t_bias.view(1, -1, 1, 1)
                y = (y - b) * gain + b
            f_t[C * int(pt_off[c]) : C * int(pt_off[c + 1])].copy_(y.reshape(-1))
        if on_gpu:  # and the features written before Warp's stream reads them
            torch.cuda.synchronize(f_t.device)
        return feat

    def _take_buffers(self) -> dict:
        """A set of the torch form's buffers no batch in flight holds, reused across batches and
        searches: fresh host memory faults on first touch, which was most of what the copies cost."""
        try:
            return self._buffers.get_nowait()
        except queue.Empty:
            return {}


def shift_array(radius: int, device: str) -> wp.array:
    """The grid-cell displacements (dx, dy) with |dx|, |dy| <= radius, (0, 0) first, as kernel #2 takes
    them (perch_warp.score_terms `shift`); radius 0 gives (0, 0) alone."""
    r = range(-int(radius), int(radius) + 1)
    d = sorted(((dx, dy) for dy in r for dx in r), key=lambda p: (p != (0, 0), p[1], p[0]))
    return wp.array(np.array(d, np.int32).reshape(-1, 2), dtype=wp.vec2i, device=device)


def exposure_array(stops: float, device: str) -> wp.array:
    """The exposure term's gains (perch_warp.score_terms `exposure`) as kernel #2 takes them, 1 first:
    2^(k / 2) for the half stops k / 2 within +-stops; 0 gives (1,) alone (no term)."""
    return wp.array(exposure_gains(stops), dtype=float, device=device)


def best_over_shifts(scores: np.ndarray, n_shifts: int) -> np.ndarray:
    """(B,) the best of each candidate's S scores, scores being S blocks of B (top_alpha_mean_device's
    order with blocks = S)."""
    return np.asarray(scores).reshape(n_shifts, -1).max(axis=0)


def point_weights(
    gain: wp.array,
    offset: wp.array | None = None,
    edge: wp.array | None = None,
    outline: float = 0.0,
    rectified: float = 0.0,
    centre: float = 0.0,
) -> PointWeights:
    """The photo's per-point maps for kernel #2, on gain's device: gain (rarity), offset (zeros when None),
    for the outline term its weight with the photo's normalised gradient per pixel (perch_warp.outline;
    edge (H, W) vec2, needed when outline > 0), and the rectified and centre terms' weights
    (perch_warp.score_terms)."""
    if not 0.0 <= rectified <= 1.0:
        raise PerchError(f"the rectified term's weight must be in [0, 1], got {rectified}")
    if not 0.0 <= centre <= 1.0:
        raise PerchError(f"the centre term's weight must be in [0, 1], got {centre}")
    if outline > 0.0 and edge is None:
        raise PerchError("the outline term needs the photo's edge map")
    pw = PointWeights()
    pw.gain = gain
    pw.offset = offset if offset is not None else wp.zeros(gain.shape, dtype=float, device=gain.device)
    pw.edge = edge if edge is not None else wp.zeros((1, 1), dtype=wp.vec2, device=gain.device)
    pw.outline = float(outline)
    pw.rectified = float(rectified)
    pw.centre = float(centre)
    return pw


def _grown(bufs: dict, name: str, n: int, device: str) -> wp.array:
    """bufs[name][:n], a float array reallocated when it holds fewer than n items."""
    if name not in bufs or bufs[name].shape[0] < n:
        bufs[name] = wp.empty(max(n, 1), dtype=float, device=device)
    return bufs[name][:n]


def crop_boxes(gboxes: np.ndarray, kernel_size: int, stride: int) -> np.ndarray:
    """Pixel boxes (x0, y0, w, h) that the windows of each grid box's (gx0, gy0, gw, gh) feature points
    cover: an unpadded stride-s convolution of the crop gives exactly those points, row by row."""
    g = np.asarray(gboxes, dtype=np.int64).reshape(-1, 4)
    live = (g[:, 2] > 0) & (g[:, 3] > 0)
    w = stride * (g[:, 2] - 1) + kernel_size
    h = stride * (g[:, 3] - 1) + kernel_size
    out = np.stack([stride * g[:, 0], stride * g[:, 1], w, h], -1)
    out[~live] = 0
    return out.astype(np.int32)


def grid_boxes(boxes: np.ndarray, kernel_size: int, stride: int) -> np.ndarray:
    """Cells (gx0, gy0, gw, gh) of the feature grid, extended beyond the image, whose centre
    pixels (half + s*gx, half + s*gy) lie inside each pixel box (x0, y0, w, h)."""
    half = kernel_size // 2
    x0, y0, w, h = (boxes[:, i].astype(np.int64) for i in range(4))
    gx0 = -((half - x0) // stride)  # ceil((x0 - half) / s)
    gy0 = -((half - y0) // stride)
    gx1 = (x0 + w - 1 - half) // stride
    gy1 = (y0 + h - 1 - half) // stride
    gw = np.where((w > 0) & (gx1 >= gx0), gx1 - gx0 + 1, 0)
    gh = np.where((h > 0) & (gy1 >= gy0), gy1 - gy0 + 1, 0)
    empty = (gw == 0) | (gh == 0)
    out = np.stack([gx0, gy0, gw, gh], -1).astype(np.int32)
    out[empty] = 0
    return out


def top_alpha_mean_device(
    values: wp.array, offsets: wp.array, alpha: float, shrink: float = 0.0, blocks: int = 1, beta: float = 0.0
) -> tuple[wp.array, wp.array]:
    """`top_alpha_mean` on the values' device (kernels/reduce.py): scores (S B,) float64 and n (S B,) int32,
    device arrays, so that one number per candidate crosses to the host instead of every point. With
    `blocks` S > 1 the values are S blocks laid out alike (kernel #2 under shifts), block s's candidate c
    at s B + c. `beta`: the share of a candidate's points k counts at least when some are HIDDEN."""
    n_cand = offsets.shape[0] - 1
    with wp.ScopedDevice(values.device):
        scores = wp.empty(blocks * n_cand, dtype=wp.float64)
        n = wp.empty(blocks * n_cand, dtype=wp.int32)
        if n_cand > 0:
            wp.launch(
                top_alpha_mean_kernel,
                dim=blocks * n_cand,
                inputs=[values, offsets, n_cand, float(alpha), float(shrink), float(beta)],
                outputs=[scores, n],
            )
    return scores, n


def top_alpha_mean(
    values: np.ndarray, offsets: np.ndarray, alpha: float, shrink: float = 0.0, beta: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Per candidate: mean of the top k = ceil(α n) of its n on-mask values (their sum over k + shrink),
    and n (the reference for `top_alpha_mean_device`, which the engine runs).

    `values` is flat with candidate c at [offsets[c], offsets[c+1]); entries at or below
    NOT_ON_MASK / 2 are off the mask. Candidates with no on-mask point score -inf. Entries at or below
    HIDDEN / 2 (kernels/hidden.py) are on the mask but hidden by another object: with V of n visible,
    k = alpha_count(α, hidden_count(β, V, n)) and the score is the sum of the best min(k, V) visible
    values over k + shrink (-inf when V = 0).
    """
    counts = np.diff(offsets).astype(np.int64)
    out_scores, out_n = np.full(len(counts), -np.inf), np.zeros(len(counts), np.int64)
    v = np.asarray(values).astype(np.float64)
    for c, (lo, hi) in enumerate(zip(offsets[:-1], offsets[1:], strict=True)):
        mine = v[int(lo) : int(hi)]
        on = mine > NOT_ON_MASK / 2
        visible = np.sort(mine[on & (mine > HIDDEN / 2)])[::-1]
        out_n[c] = n = int(on.sum())
        if len(visible):
            k = alpha_count(alpha, hidden_count(beta, len(visible), n))
            out_scores[c] = visible[:k].sum() / (k + shrink)
    return out_scores, out_n


def hidden_count(beta: float, visible: int, n: int) -> int:
    """The count the top-α share is taken of when `visible` of a candidate's n points are not hidden: n
    when none is, else max(visible, ceil(β n)) (kernels/reduce.py)."""
    if visible == n:
        return n
    return max(visible, math.ceil(beta * n - 1e-9))


def alpha_count(alpha: float, n: int) -> int:
    """How many of n values the top-α mean averages (at least one)."""
    return max(1, math.ceil(alpha * n - 1e-9))
