"""The per-photo scoring service: every search's only way to score or bound candidate poses.

It owns one photo on the device (features, the point-weight maps gain/offset, the ceiling map), the
camera, table and resting pose, the renderer this search uses, batching over a thread pool on the
CPU, the stage timings and the progress bar. `score(poses)` and `bound(poses)` take table-frame
(x_m, y_m, yaw_rad) arrays or a PoseSource (set up a chunk at a time) and return one float64 per
pose; what they cost (batches, rays) is added to the SearchStats the caller passes.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import warp as wp

from ..bound import silhouette_bounds
from ..camera import Camera
from ..errors import PerchError
from ..features import FeatureWeights
from ..footing import footing, footprint_radius_m, likeness_map
from ..hidden import HiddenPoints, hide
from ..image import check_rgb
from ..kernels.features import NOT_ON_MASK, PointWeights
from ..kernels.render import Shading
from ..outline import edge_ceiling, edge_map
from ..rarity import rarity_and_labels, unit_responses
from ..render import MIN_DEPTH_M, BoxProjector, Renderer, point_layout
from ..score import (
    FeatureScorer,
    best_over_shifts,
    grid_boxes,
    grid_shape,
    point_weights,
    top_alpha_mean_device,
)
from ..score_terms import ScoreTerms, background_offset, tone_gains
from ..search_space import SearchSpace
from ..table import RestingPose, Table, model_to_camera
from .known import KnownScores

# Candidates whose poses and boxes are set up at once (host and device memory): a search keeps
# a few numbers per candidate of its space (score, bound, box size) and nothing larger, so no
# step needs all candidates' poses at once, however large the space.
SETUP_CHUNK = 1 << 17


@dataclass
class SearchStats:
    """What one search cost: batches launched, pixels ray-cast by kernel #1 (the rendered boxes'
    areas) and rays cast for silhouette bounds (one per feature point)."""

    batches: int = 0
    rays: int = 0
    bound_rays: int = 0


class PoseSource:
    """Candidates 0..n-1, their table-frame (x_m, y_m, yaw_rad) given by at(indices); their camera
    poses and boxes are set up a chunk at a time (ScoringService.setup)."""

    def __init__(self, n: int, at) -> None:
        self.n, self.at = n, at

    @classmethod
    def of_space(cls, space: SearchSpace) -> PoseSource:
        return cls(len(space), space.at)

    @classmethod
    def of_arrays(cls, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> PoseSource:
        return cls(len(x), lambda i: (x[i], y[i], yaw[i]))

    def chunks(self):
        for lo in range(0, self.n, SETUP_CHUNK):
            yield np.arange(lo, min(self.n, lo + SETUP_CHUNK))


class Candidates(NamedTuple):
    """Candidates set up for scoring: model-to-camera R (N, 3, 3), t (N, 3) metres, pixel boxes,
    feature-grid boxes, the indices of those showing at least one feature point, and what each one's
    place alone adds to its score and bound (the footing term, perch_warp.footing; None without it)."""

    R: np.ndarray
    tr: np.ndarray
    boxes: np.ndarray
    gboxes: np.ndarray
    live: np.ndarray
    prior: np.ndarray | None = None


@dataclass
class Photo:
    """One photo on the device: image, feature map, feature norms, and on the feature grid the
    maps kernel #2 weighs a point's cosine by (gain = rarity, offset) and their ceiling = gain - offset,
    each point's largest possible value (the pruned search's bound)."""

    image: wp.array
    obs: wp.array
    norm: wp.array
    weights: PointWeights
    ceiling: wp.array
    rows: int
    cols: int
    pooled: dict = dataclasses.field(default_factory=dict)
    likeness: np.ndarray | None = None  # (rows, cols) on the host: the footing term's map (perch_warp.footing)

    def ceiling_within(self, radius: int) -> wp.array:
        """The ceiling max-pooled over the (2 radius + 1)^2 grid cells around each cell, zero beyond
        the grid: the bound of a score with that shift (perch_warp.score_terms); the ceiling itself for
        radius 0. Made once per radius."""
        if radius == 0:
            return self.ceiling
        if radius not in self.pooled:
            c = np.pad(self.ceiling.numpy(), radius, constant_values=0.0)
            n = 2 * radius + 1
            windows = np.lib.stride_tricks.sliding_window_view(c, (n, n))
            pooled = np.ascontiguousarray(windows.max(axis=(2, 3)), dtype=np.float32)
            self.pooled[radius] = wp.array(pooled, dtype=float, device=self.ceiling.device)
        return self.pooled[radius]


@dataclass(frozen=True)
class Backends:
    """What is built once per mesh (and weights, device): scorer, box projector (the renderers are
    the engine's, one of them chosen per search)."""

    scorer: FeatureScorer
    boxes: BoxProjector
    weights: FeatureWeights
    device: str


def batch_pixels(device: str) -> int:
    """Rays per batch sized to the device: ~13 bytes per rendered pixel plus scores; keep a batch to
    ~1/8 of free GPU memory."""
    if device.startswith("cuda"):
        free = wp.get_device(device).free_memory
        return int(max(1 << 22, min(1 << 28, free // 8 // 16)))
    return 1 << 22


def cpu_threads(device: str, configured: int | None) -> int:
    """Threads scoring batches at once: 1 on a GPU (one stream), else the configured or one per core."""
    if not wp.get_device(device).is_cpu:
        return 1
    if configured is not None:
        return configured
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def lap(device: str, timings: dict, stage: str, t0: float) -> float:
    """Add the seconds since t0 (device synchronised) to timings[stage]; returns now."""
    wp.synchronize_device(device)
    t1 = time.perf_counter()
    timings[stage] = timings.get(stage, 0.0) + (t1 - t0)
    return t1


def photo_on_device(backends: Backends, config, terms: ScoreTerms, image_rgb, camera: Camera, timings: dict) -> Photo:
    """The photo's feature map, norms and rarity, on the device (once per photo)."""
    image_rgb = check_rgb(image_rgb)
    if image_rgb.shape[:2] != (camera.height, camera.width):
        raise PerchError(
            f"image is {image_rgb.shape[1]}x{image_rgb.shape[0]} but the camera is {camera.width}x{camera.height}"
        )
    ks = backends.weights.kernel_size
    rows, cols = grid_shape(camera.width, camera.height, ks, config.stride)
    if rows < 1 or cols < 1:
        raise PerchError(f"image {camera.width}x{camera.height} is smaller than the {ks}x{ks} feature window")
    t = time.perf_counter()
    image = backends.scorer.image_to_device(image_rgb)
    obs = backends.scorer.observed_features(image)
    t = lap(backends.device, timings, "photo_features", t)
    feats = obs.numpy().reshape(rows * cols, -1)
    space = unit_responses(feats, backends.scorer.folded_bias) if terms.cluster == "direction" else feats
    rar, labels = rarity_and_labels(space, config.clusters, config.seed, terms.rarity, terms.inits)
    offset = background_offset(feats, labels, rar, terms.background)
    ceiling = (rar - offset).reshape(rows, cols)
    edge = None
    if terms.outline > 0.0:  # the outline term (perch_warp.outline): its edge map and its share of the ceiling
        edge = edge_map(image_rgb)
        ceiling = ceiling + terms.outline * edge_ceiling(edge, rows, cols, ks, config.stride)
    norms = np.linalg.norm(feats.astype(np.float64), axis=1).reshape(rows, cols).astype(np.float32)
    with wp.ScopedDevice(backends.device):
        gain = wp.array(rar.reshape(rows, cols), dtype=float)
        pw = point_weights(
            gain,
            wp.array(offset.reshape(rows, cols), dtype=float),
            None if edge is None else wp.array(edge, dtype=wp.vec2),
            terms.outline,
            terms.rectified,
            terms.centre,
        )
        # The thesis's ceiling is the rarity itself: the same array, so its bounds stay bit for bit.
        plain = terms.background == 0.0 and terms.outline == 0.0
        ceil = gain if plain else wp.array(ceiling.astype(np.float32), dtype=float)
        photo = Photo(image, obs, wp.array(norms, dtype=float), pw, ceil, rows, cols)
    if terms.table > 0.0:
        photo.likeness = likeness_map(feats, labels, rows, cols)
    lap(backends.device, timings, "rarity", t)
    return photo


def _as_source(poses) -> PoseSource:
    if isinstance(poses, PoseSource):
        return poses
    x, y, yaw = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in poses)
    return PoseSource.of_arrays(x, y, yaw)


@dataclass
class ScoringService:
    """Scores and silhouette bounds of candidate poses in one photo (see the module doc)."""

    backends: Backends
    config: object  # config.EngineConfig
    terms: ScoreTerms
    photo: Photo
    camera: Camera
    table: Table
    resting: RestingPose
    renderer: Renderer  # the form of kernel #1 this search uses
    timings: dict = dataclasses.field(default_factory=dict)
    bar: object = None  # a tqdm bar or None
    # What other objects hide (perch_warp.hidden): their points are left out of the score and its bound.
    hidden: HiddenPoints | None = None
    # Plain scores and bounds of this object in this photo kept by an earlier search (search/known.py):
    # taken where no point can be hidden, and this search's plain values kept there in turn.
    known: KnownScores | None = None

    def __post_init__(self) -> None:
        if self.hidden is not None and tuple(self.hidden.near_m.shape) != (self.photo.rows, self.photo.cols):
            raise PerchError(
                f"the occluder map is {self.hidden.near_m.shape} cells but the photo's feature grid is "
                f"{(self.photo.rows, self.photo.cols)}: make it on this photo's grid (after image_scale)"
            )

    @property
    def beta(self) -> float:
        """The reduction's beta (kernels/reduce.py): 0 without hidden points, where it plays no part."""
        return 0.0 if self.hidden is None else self.hidden.beta

    def quiet(self, timings: dict | None = None) -> ScoringService:
        """The same service without a progress bar, its stage seconds into `timings` (a new dict by default)."""
        return dataclasses.replace(self, timings={} if timings is None else timings, bar=None)

    def refining(self) -> ScoringService:
        """The quiet service that scores below the grid: the same score without the grid's shift
        tolerance (perch_warp.score_terms `shift`), so a refined pose and its score are the plain score's."""
        return dataclasses.replace(self.quiet(), terms=self.terms.below_grid())

    @property
    def device(self) -> str:
        return self.backends.device

    def threads(self) -> int:
        return cpu_threads(self.device, self.config.cpu_threads)

    def budget(self) -> int:
        """Rays (pixels or feature points) per batch: the config's, else sized to the device."""
        return self.config.batch_pixels or batch_pixels(self.device)

    def lap(self, stage: str, t0: float, timings: dict | None = None) -> float:
        return lap(self.device, self.timings if timings is None else timings, stage, t0)

    def shading(self) -> Shading:
        """Kernel #1's light (score term shade): from above the table, whose normal is the resting
        pose's third row in the model frame (the same for every x, y and yaw on the table)."""
        return self.renderer.dmesh.shading(self.resting.R_rest[2], self.terms.shade)

    def score(self, poses, stats: SearchStats | None = None) -> np.ndarray:
        """Score (N,) float64 of each pose (x_m, y_m, yaw_rad arrays or a PoseSource), set up a chunk at
        a time; -inf where it shows no feature point (those count as done on the progress bar at once)."""
        poses, stats, bar = _as_source(poses), stats or SearchStats(), self.bar
        scores = np.full(poses.n, -np.inf)
        if bar is not None:
            bar.total += poses.n
            bar.refresh()
        for idx in poses.chunks():
            c = self.setup(poses, idx)
            if bar is not None:
                bar.update(len(idx) - len(c.live))
            part = np.full(len(idx), -np.inf)
            self.score_some(c, c.live, part, stats)
            scores[idx] = part
        return scores

    def bound(self, poses, stats: SearchStats | None = None) -> np.ndarray:
        """Silhouette bound (N,) float64 of each pose's score (perch_warp.bound); -inf where it shows no
        feature point."""
        poses, stats = _as_source(poses), stats or SearchStats()
        bounds = np.full(poses.n, -np.inf)
        for idx in poses.chunks():
            c = self.setup(poses, idx)
            part = np.full(len(idx), -np.inf)
            self.bound_some(c, c.live, part, stats)
            bounds[idx] = part
        return bounds

    def candidates(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> Candidates:
        """Poses, pixel boxes and feature-grid boxes of candidates (x_m, y_m, yaw_rad arrays) and the
        indices of those that show at least one feature point and stand on the table's extent (if any)."""
        t = time.perf_counter()
        R, tr = model_to_camera(self.table, self.resting, x, y, yaw)
        boxes = self.backends.boxes(self.camera, R, tr)  # = project_boxes(camera, hull_m, R, tr), on the device
        if np.any(boxes[:, 2] < 0):
            n_bad = int((boxes[:, 2] < 0).sum())
            raise PerchError(
                f"{n_bad} of {len(boxes)} candidate poses set up together are behind or within {MIN_DEPTH_M} m "
                "of the camera: check the table frame and the search ranges"
            )
        gboxes = grid_boxes(boxes, self.backends.weights.kernel_size, self.config.stride)
        live = np.flatnonzero(gboxes[:, 2] * gboxes[:, 3] > 0)
        if self.table.extent_m is not None:  # off the table top: no object rests there, never scored
            live = live[self.table.contains(np.asarray(x)[live], np.asarray(y)[live])]
        prior = None
        if self.terms.table > 0.0:
            radius = footprint_radius_m(self.backends.boxes.hull_m, self.resting)
            ks, stride = self.backends.weights.kernel_size, self.config.stride
            # Once per place: a chunk holds each place at every yaw, and the footing ignores the yaw.
            xy = np.stack(np.broadcast_arrays(np.atleast_1d(x), np.atleast_1d(y)), axis=1)
            places, at = np.unique(xy, axis=0, return_inverse=True)
            where = footing(self.table, self.camera, self.photo.likeness, *places.T, radius, ks, stride)
            prior = self.terms.table * np.broadcast_to(where[at.ravel()], (len(R),))
        self.lap("candidates", t)
        return Candidates(R, tr, boxes, gboxes, live, prior)

    def setup(self, poses: PoseSource, idx: np.ndarray) -> Candidates:
        """candidates() of candidates idx of poses (a chunk: the arrays are idx's, in its order)."""
        return self.candidates(*poses.at(idx))

    def score_some(self, c: Candidates, idx, out: np.ndarray, stats: SearchStats, progress: bool = True) -> None:
        """out[idx] = the scores of candidates idx of c (render, features, top-α), in batches; with known
        scores (search/known.py), those of candidates no hidden point can touch are taken, not scored."""
        idx = np.asarray(idx, dtype=np.int64)
        bar = self.bar if progress else None
        todo, plain = self._take_known("score", c, idx, out)
        if bar is not None and len(todo) < len(idx):
            bar.update(len(idx) - len(todo))
        sizes = c.boxes[todo, 2].astype(np.int64) * c.boxes[todo, 3]
        stats.rays += int(sizes.sum())
        work = functools.partial(self._score_batch, c, *self._variants())
        self._batched(work, todo, sizes, out, stats, bar)
        self._keep_known("score", c, todo[plain], out)
        if c.prior is not None:
            out[idx] += c.prior[idx]

    def _take_known(self, kind: str, c: Candidates, idx: np.ndarray, out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """out[i] = the known plain value (search/known.py) of each candidate i of idx that no hidden point
        can touch, where one is known. Returns the rest of idx, in order, to compute, and which of them
        are plain (their values to keep): decided once per call."""
        if self.known is None:  # nothing to take or keep
            return idx, np.zeros(len(idx), dtype=bool)
        if self.hidden is None:
            plain = np.ones(len(idx), dtype=bool)
        else:
            plain = self.hidden.untouched(c.gboxes[idx], c.tr[idx])
        left = np.ones(len(idx), dtype=bool)
        left[np.flatnonzero(plain)[self.known.take(self, kind, c.R, c.tr, out, idx[plain])]] = False
        return idx[left], plain[left]

    def _keep_known(self, kind: str, c: Candidates, idx: np.ndarray, out: np.ndarray) -> None:
        """Keep the computed plain values out[idx]; before the place's own term, which is added per call."""
        if self.known is not None:
            self.known.keep(self, kind, c.R, c.tr, out, idx)

    def bound_some(self, c: Candidates, idx, out: np.ndarray, stats: SearchStats) -> None:
        """out[idx] = the silhouette bounds of candidates idx of c (perch_warp.bound), in batches; with
        known values (search/known.py), those of candidates no hidden point can touch are taken."""
        idx = np.asarray(idx, dtype=np.int64)
        todo, plain = self._take_known("bound", c, idx, out)
        sizes = c.gboxes[todo, 2].astype(np.int64) * c.gboxes[todo, 3]  # one ray per feature point
        stats.bound_rays += int(sizes.sum())
        # Pooled here, once, not by the batches' threads.
        work = functools.partial(self._bound_batch, c, self.photo.ceiling_within(self.terms.shift))
        self._batched(work, todo, sizes, out, stats, None)
        self._keep_known("bound", c, todo[plain], out)
        if c.prior is not None:  # the place's own term, exactly: the bound stays as tight
            out[idx] += c.prior[idx]

    def _score_batch(
        self, c: Candidates, shifts: wp.array, gains: wp.array, tone: np.ndarray, idx
    ) -> tuple[np.ndarray, dict[str, float]]:
        """Candidates `idx`: render (kernel #1) -> features x similarity x rarity (kernel #2, under each
        of `shifts`, exposure `gains` and `tone` exposures) -> top-α mean (the best of them); their scores on
        the host and the seconds each stage took."""
        laps: dict[str, float] = {}
        vals, pt_off = self._point_values(c, shifts, gains, tone, idx, laps)
        t = time.perf_counter()
        n_blocks = shifts.shape[0] * gains.shape[0] * len(tone)
        if self.hidden is not None:
            ks, stride = self.backends.weights.kernel_size, self.config.stride
            pts = point_layout(c.boxes[idx], c.gboxes[idx], ks, stride, self.device)
            hide(vals, pts, c.tr[idx], self.hidden, n_blocks)
        # The same kernel on every device, so CPU and GPU runs take the same path to a score.
        cfg = self.config
        batch_scores, _ = top_alpha_mean_device(vals, pt_off, cfg.alpha, self.terms.shrink, n_blocks, self.beta)
        t = self.lap("reduction", t, laps)
        # One float per candidate (and shift and gain) crosses to the host, not every feature point.
        out = best_over_shifts(batch_scores.numpy(), n_blocks)
        self.lap("transfer", t, laps)
        return out, laps

    def _point_values(
        self, c: Candidates, shifts: wp.array, gains: wp.array, tone: np.ndarray, idx, laps: dict[str, float]
    ) -> tuple[wp.array, wp.array]:
        """Candidates `idx`: render (kernel #1) -> each feature point's value (kernel #2), on the device:
        values and per-candidate offsets (FeatureScorer.score_points' layout), the stages' seconds into laps."""
        photo, scorer = self.photo, self.backends.scorer
        t = time.perf_counter()
        batch = self.renderer.render(self.camera, c.R[idx], c.tr[idx], c.boxes[idx], self.shading())
        t = self.lap("render", t, laps)
        vals, pt_off = scorer.score_points(
            photo.image, batch, c.gboxes[idx], photo.obs, photo.norm, photo.weights, shifts, gains, tone
        )
        self.lap("features_score", t, laps)
        return vals, pt_off

    def _variants(self) -> tuple[wp.array, wp.array, np.ndarray]:
        """What kernel #2 scores each point under: the grid's shifts, the exposure gains, the tone exposures."""
        scorer = self.backends.scorer
        return scorer.shifts(self.terms.shift), scorer.gains(self.terms.exposure), tone_gains(self.terms.tone)

    def point_values(self, poses, pixels: bool = False) -> list:
        """Each pose's feature-point values, float32, one per point of its silhouette (empty where it shows
        none); poses as for score(): table-frame x_m, y_m, yaw_rad arrays or a PoseSource. They are the
        numbers whose top-α mean is its score, kept so that other reductions can be studied on them
        (tools/score_study.py values). Only for a score with one value per point: below the grid
        (`refining()`, no shift tolerance) and without the exposure or tone variants. A place's table
        term (c.prior) is added to a score after the reduction and is not among them. With `pixels`,
        each pose's entry is (values, uv): uv (n, 2) int32 the points' photo pixels (column, row), so
        that a study can tell which points another object hides. The service's hidden points
        (perch_warp.hidden) are not marked here: every value is the point's own."""
        shifts, gains, tone = self._variants()
        if shifts.shape[0] * gains.shape[0] * len(tone) != 1:
            raise PerchError(
                f"point values need one value per point; score {self.terms.spec()!r} has several "
                "(shift, exposure or tone): take them from the refining service (below the grid)"
            )
        poses = _as_source(poses)
        out = np.empty(poses.n, dtype=object)
        none = np.zeros(0, np.float32)
        for i in range(poses.n):  # poses that show no feature point keep it
            out[i] = (none, np.zeros((0, 2), np.int32)) if pixels else none
        for idx in poses.chunks():
            c = self.setup(poses, idx)
            part = out[idx]  # a copy (fancy indexing), written back below
            sizes = c.boxes[c.live, 2].astype(np.int64) * c.boxes[c.live, 3]
            work = functools.partial(self._values_batch, c, shifts, gains, tone, pixels=pixels)
            self._batched(work, c.live, sizes, part, SearchStats(), None)
            out[idx] = part
        return list(out)

    def _values_batch(
        self, c: Candidates, shifts: wp.array, gains: wp.array, tone: np.ndarray, idx, pixels: bool = False
    ) -> tuple[np.ndarray, dict[str, float]]:
        """Candidates `idx`: their on-mask feature-point values on the host, one array each (with
        `pixels`, (values, uv) each; an object array, for _batched), and the seconds each stage took."""
        laps: dict[str, float] = {}
        vals, pt_off = self._point_values(c, shifts, gains, tone, idx, laps)
        v, o = vals.numpy(), pt_off.numpy()
        half, stride = self.backends.weights.kernel_size // 2, self.config.stride
        out = np.empty(len(idx), dtype=object)
        for a, ci in enumerate(idx):
            x = v[o[a] : o[a + 1]]
            on = x > NOT_ON_MASK / 2
            if not pixels:
                out[a] = x[on].copy()
                continue
            # kernels/features.py PointLayout: the grid box's cells row by row, cell (gx, gy) at pixel
            # (half + stride gx, half + stride gy)
            gx0, gy0, gw, _ = (int(g) for g in c.gboxes[ci])
            local = np.flatnonzero(on)
            uv = np.stack([half + stride * (gx0 + local % gw), half + stride * (gy0 + local // gw)], 1)
            out[a] = (x[on].copy(), uv.astype(np.int32))
        return out, laps

    def _bound_batch(self, c: Candidates, ceiling: wp.array, idx) -> tuple[np.ndarray, dict[str, float]]:
        """Candidates `idx`: upper bounds of their scores from their silhouettes (`ceiling`: the photo's
        ceiling map for this score, Photo.ceiling_within), and the seconds taken."""
        laps: dict[str, float] = {}
        t = time.perf_counter()
        cfg = self.config
        out = silhouette_bounds(
            self.renderer,
            self.camera,
            c.R[idx],
            c.tr[idx],
            c.boxes[idx],
            c.gboxes[idx],
            ceiling,
            self.backends.weights.kernel_size,
            cfg.stride,
            cfg.alpha,
            self.terms.shrink,
            self.hidden,
        )
        self.lap("bound", t, laps)
        return out, laps

    def _batched(self, work, idx: np.ndarray, sizes: np.ndarray, out: np.ndarray, stats: SearchStats, bar) -> None:
        """out[b] = work(b)[0] for batches b of idx (their sizes, in rays, within the device's budget),
        on a thread pool on the CPU; work's stage seconds are added to the timings."""
        budget = self.budget()
        n_rays = int(sizes.sum())
        threads = self.threads()
        if threads > 1:
            # Smaller batches so that every thread has some and those in flight together hold
            # about one budget's pixels; not below 64 Ki pixels (launch overhead) unless the budget is.
            budget = max(min(budget, 1 << 16), min(budget // threads, -(-n_rays // (2 * threads))))
        batches = [idx[lo:hi] for lo, hi in split_by_budget(sizes, budget)]
        stats.batches += len(batches)
        threads = min(threads, len(batches))
        timings = self.timings

        def done(b: np.ndarray, values: np.ndarray, laps: dict[str, float]) -> None:
            out[b] = values  # by candidate index: the order batches finish in does not matter
            for stage, sec in laps.items():
                timings[stage] = timings.get(stage, 0.0) + sec
            if bar is not None:
                bar.update(len(b))

        with self.backends.scorer.conv_settings():
            if threads <= 1:
                for b in batches:
                    done(b, *work(b))
                return
            _on_pool(work, batches, done, threads, self.device)


def _on_pool(work, batches: list, done, threads: int, device: str) -> None:
    """done(b, *work(b)) for each batch, the work on a pool of `threads`. Each batch's arrays are its
    own (the renderer and scorer allocate per call and keep no per-call state). A stage's time is then
    the sum over threads of its per-batch times, i.e. CPU time, which can exceed the wall time."""
    with _default_device(device), ThreadPoolExecutor(threads, thread_name_prefix="perch-score") as pool:
        futures = {pool.submit(work, b): b for b in batches}
        try:
            for f in as_completed(futures):
                done(futures[f], *f.result())
        except BaseException:
            for f in futures:
                f.cancel()
            raise


@contextmanager
def _default_device(device: str):
    """`device` as Warp's default device while the pool runs. wp.ScopedDevice (used by the renderer and
    scorer) saves and restores one process-wide default, so threads entering and leaving it at once
    would hand each other a stale default; with the default already `device` they only rewrite it."""
    saved = wp.get_device()
    if saved == wp.get_device(device):
        yield
        return
    wp.set_device(device)
    try:
        yield
    finally:
        wp.set_device(saved)


def split_by_budget(sizes: np.ndarray, budget: int) -> list[tuple[int, int]]:
    """Consecutive [lo, hi) ranges whose summed sizes stay within budget (a lone oversize item gets its own)."""
    out = []
    lo = 0
    acc = 0
    for i, s in enumerate(sizes.tolist()):
        if acc + s > budget and i > lo:
            out.append((lo, i))
            lo, acc = i, 0
        acc += s
    if lo < len(sizes):
        out.append((lo, len(sizes)))
    return out
