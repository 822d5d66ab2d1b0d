"""The search engine: build once per mesh (and weights, device), call once per photo.

Stages: photo features -> rarity (k-means) -> candidate poses and their boxes
(kernels/boxes.py) -> per batch: render (kernel #1) -> features x similarity x
rarity (kernel #2) -> top-α mean (kernels/reduce.py) -> best pose. Only boxes and
one score per candidate come back to the host.
"""

from __future__ import annotations

import functools
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import warp as wp

from .bound import next_to_score, silhouette_bounds
from .camera import Camera
from .errors import PerchError
from .features import FeatureWeights
from .image import check_rgb
from .kernels.features import PointWeights
from .mesh import ObjectMesh
from .peaks import distinct_peaks, peak_pool
from .rarity import rarity_and_labels
from .refine import cell_space
from .render import MIN_DEPTH_M, RENDERERS, BoxProjector, MeshRenderer, auto_renderer
from .result import Candidate, Result
from .score import CONVS, FeatureScorer, auto_conv, grid_boxes, grid_shape, point_weights, top_alpha_mean_device
from .score_terms import background_offset, parse_score
from .search_space import FULL_CIRCLE, SearchSpace
from .table import RestingPose, Table, model_to_camera, pose_matrix

SEARCHES = ("auto", "exhaustive", "pruned", "coarse-to-fine")

# Candidates whose poses and boxes are set up at once (host and device memory): a search keeps
# a few numbers per candidate of its space (score, bound, box size) and nothing larger, so no
# step needs all candidates' poses at once, however large the space.
SETUP_CHUNK = 1 << 17


@dataclass(frozen=True)
class EngineConfig:
    """Method parameters (thesis §3.2): feature stride (px), occlusion limit α, k-means clusters and seed."""

    stride: int = 4
    alpha: float = 0.5
    clusters: int = 20
    seed: int = 0
    top_k: int = 5
    relu: bool = False
    batch_pixels: int | None = None  # rendered pixels per batch; None: sized to the device
    # "exhaustive": score every grid pose; "pruned": the same top-k, scoring only candidates whose
    # silhouette bound can reach it (Engine._pruned); "coarse-to-fine": a pyramid (Engine._coarse_to_fine);
    # "auto": pruned on the CPU (measured faster there, docs/performance.md), exhaustive on a GPU
    # (the pruned search's GPU speed is not measured yet). Both give the same top-k.
    search: str = "auto"
    coarse_xy_m: float = 0.02  # coarse-to-fine: the first lattice's x/y step
    coarse_yaw_rad: float = math.radians(10.0)  # coarse-to-fine: the first lattice's yaw step
    beam: int = 32  # coarse-to-fine: how many best candidates each finer level refines
    max_polish: int = 10  # coarse-to-fine: hill-climbing rounds on the final grid
    image_scale: float = 1.0  # search on the photo resized by this factor (camera scaled alike): cheaper on a CPU
    # coarse-to-fine: leave out lattice points whose silhouette bound cannot reach the beam (perch_warp.bound);
    # the same result as without, scoring fewer
    pyramid_bounds: bool = True
    # CPU device only: batches scored at once on this many threads (a Warp CPU launch runs on one
    # core but releases the GIL). None: one per available core; 1: one batch after another.
    cpu_threads: int | None = None
    # After the grid search, search the best grid pose's cell (one grid step either side) on a grid
    # of at most refine_xy_m and refine_yaw_rad (perch_warp.refine): poses between the grid's.
    refine: bool = True
    refine_xy_m: float = 0.002
    refine_yaw_rad: float = math.radians(1.0)
    refine_cells: int = 1  # grid steps either side of the best grid pose that the refinement searches
    # Refine this many distinct peaks of the grid search (perch_warp.peaks), not only its best: the best
    # refined pose wins (narrow peaks of small objects can lose on the grid and win refined). 1: the grid's best.
    refine_peaks: int = 1
    # How kernel #1 finds each ray's surface (perch_warp.render): "bvh", "raster" (the same images),
    # or "auto": per search on the CPU, raster unless the mesh has many faces per pixel of the
    # candidates' boxes (render.auto_renderer); bvh on a GPU (the raster form is not measured there).
    renderer: str = "auto"
    # How kernel #2 convolves the candidates' windows (perch_warp.score): "warp", "torch" (conv2d on
    # each candidate's composited crop; the same values up to float rounding), or "auto": torch on the
    # CPU (measured faster there), warp on a GPU (torch is not measured there).
    conv: str = "auto"
    # What a candidate's score is made of (perch_warp.score_terms): a name ("thesis": the thesis's
    # formula) or terms over the thesis's, e.g. "surround=fill,shrink=16".
    score: str = "thesis"

    def __post_init__(self) -> None:
        parse_score(self.score)  # fails early, with the terms it knows
        if not (0.0 < self.alpha <= 1.0) or not math.isfinite(self.alpha):
            raise PerchError(f"alpha (occlusion limit) must be in (0, 1], got {self.alpha}")
        if self.stride < 1:
            raise PerchError(f"stride must be a positive number of pixels, got {self.stride}")
        if self.clusters < 1:
            raise PerchError(f"clusters must be at least 1, got {self.clusters}")
        if self.top_k < 1:
            raise PerchError(f"top_k must be at least 1, got {self.top_k}")
        if not (0.0 < self.image_scale <= 1.0):
            raise PerchError(f"image scale must be in (0, 1], got {self.image_scale}")
        if self.search not in SEARCHES:
            raise PerchError(f"search must be one of {', '.join(SEARCHES)}, got {self.search!r}")
        if self.beam < 1 or self.coarse_xy_m <= 0 or self.coarse_yaw_rad <= 0:
            raise PerchError("coarse-to-fine needs beam >= 1 and positive coarse steps")
        if not (self.refine_xy_m > 0 and self.refine_yaw_rad > 0):
            raise PerchError(
                "refinement targets (--refine-xy, --refine-yaw) must be positive, "
                f"got {self.refine_xy_m} m and {math.degrees(self.refine_yaw_rad)} deg"
            )
        if self.refine_peaks < 1:
            raise PerchError(f"refine_peaks (--refine-peaks) must be at least 1, got {self.refine_peaks}")
        if self.refine_cells < 1:
            raise PerchError(f"refine_cells (--refine-cells) must be at least 1, got {self.refine_cells}")
        if self.conv not in CONVS:
            raise PerchError(f"conv (--conv) must be one of {', '.join(CONVS)}, got {self.conv!r}")
        if self.renderer not in RENDERERS:
            raise PerchError(f"renderer (--renderer) must be one of {', '.join(RENDERERS)}, got {self.renderer!r}")
        if self.cpu_threads is not None and self.cpu_threads < 1:
            raise PerchError(
                f"cpu_threads (--cpu-threads) must be at least 1, or None for one per core; got {self.cpu_threads}"
            )


class _Poses:
    """Candidates 0..n-1 of a search, their table-frame (x_m, y_m, yaw_rad) given by at(indices);
    their camera poses and boxes are set up a chunk at a time (Engine._setup)."""

    def __init__(self, n: int, at) -> None:
        self.n, self.at = n, at

    @classmethod
    def of_space(cls, space: SearchSpace) -> _Poses:
        return cls(len(space), space.at)

    @classmethod
    def of_arrays(cls, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> _Poses:
        return cls(len(x), lambda i: (x[i], y[i], yaw[i]))

    def chunks(self):
        for lo in range(0, self.n, SETUP_CHUNK):
            yield np.arange(lo, min(self.n, lo + SETUP_CHUNK))


@dataclass
class _Photo:
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


def default_device() -> str:
    """A CUDA GPU when Warp sees one, else the CPU (callers report which)."""
    return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"


def _batch_pixels(device: str) -> int:
    # ~13 bytes per rendered pixel plus scores; keep a batch to ~1/8 of free GPU memory.
    if device.startswith("cuda"):
        free = wp.get_device(device).free_memory
        return int(max(1 << 22, min(1 << 28, free // 8 // 16)))
    return 1 << 22


class Engine:
    """RGB-only (x, y, yaw) search for one object (PERCH Color Only on Warp)."""

    def __init__(
        self,
        mesh: ObjectMesh,
        weights: FeatureWeights,
        device: str | None = None,
        config: EngineConfig | None = None,
    ):
        wp.config.log_level = wp.LOG_WARNING  # module-build chatter is not for users
        wp.init()
        self.device = device or default_device()
        try:
            wp.get_device(self.device)
        except Exception:
            raise PerchError(f"Warp device {self.device!r} is not available (try --device cpu)") from None
        self.config = config or EngineConfig()
        self.mesh = mesh
        self.weights = weights
        t0 = time.perf_counter()
        self.renderer = MeshRenderer(
            mesh, self.device, "bvh" if self.config.renderer == "auto" else self.config.renderer
        )
        conv = self.config.conv if self.config.conv != "auto" else auto_conv(self.device)
        self.score_name, self.terms = parse_score(self.config.score)  # perch_warp.score_terms
        self.scorer = FeatureScorer(
            weights, self.device, self.config.stride, self.config.relu, conv, surround=self.terms.surround
        )
        self.scorer.warm_up()
        # Build now: compile time is not a search stage's.
        for module in ("render", "raster", "boxes", "reduce", "bound"):
            wp.load_module(f"perch_warp.kernels.{module}", device=self.device)
        self.hull_m = mesh.hull_points_m()
        self.boxes = BoxProjector(self.hull_m, self.device)
        self.setup_s = time.perf_counter() - t0

    @property
    def search(self) -> str:
        """The search this engine runs: the config's, with "auto" resolved for the device."""
        return self.config.search if self.config.search != "auto" else _auto_search(self.device)

    def render(self, camera: Camera, T_m2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full-image rendering of one pose: RGB float32 (H, W, 3) in [0, 1], mask bool (H, W)."""
        T = np.asarray(T_m2c, dtype=np.float64)
        return self.renderer.render_image(camera, T[:3, :3], T[:3, 3])

    def estimate(
        self,
        image_rgb: np.ndarray,
        camera: Camera,
        table: Table,
        resting: RestingPose,
        space: SearchSpace,
        progress: bool = False,
        probe: tuple[float, float, float] | None = None,
    ) -> Result:
        """Best (x, y, yaw) of the object in the photo; see the module doc for the stages.

        `probe` (x_m, y_m, yaw_rad, table frame), for analysis only: after the search, the best pose
        and score within that pose's cell (one grid step either side at the refinement's resolution,
        not cut to the space) on the same photo, in info["probe"]; it never changes the answer."""
        cfg = self.config
        timings: dict[str, float] = {}
        image_rgb, camera = self._begin(image_rgb, camera)
        renderer_info = self._pick_renderer(camera, table, resting, space)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=0, unit="pose", desc=f"search on {self.device}", leave=False)
        t_start = time.perf_counter()
        try:
            photo = self._photo(image_rgb, camera, timings)
            extra: dict = {}
            search = self.search
            flat = None  # scores[i] is grid candidate flat[i]; None: candidate i
            if search == "exhaustive":
                scores = self._score_poses(photo, camera, table, resting, _Poses.of_space(space), timings, bar)
                evaluated = len(space)
            elif search == "pruned":
                scores, extra = self._pruned(photo, camera, table, resting, space, timings, bar)
                evaluated = extra["scored"]
            else:
                flat, scores, levels = self._coarse_to_fine(photo, camera, table, resting, space, timings, bar)
                evaluated = len(flat)
                extra = {"levels": levels}
            if not np.isfinite(scores).any():
                raise PerchError(f"the search grid projects outside the image ({space.describe()})")
            # Stable order: ties go to the earlier candidate, so results are reproducible.
            order = _top_indices(scores, self._pool())
            x, y, yaw = space.at(order if flat is None else flat[order])
            top = [(float(x[n]), float(y[n]), float(yaw[n]), float(scores[i])) for n, i in enumerate(order)]
            if cfg.refine:
                top, extra["refine"] = self._refine_peaks(photo, camera, table, resting, space, top, timings)
            top = top[: cfg.top_k]
            if probe is not None:
                extra["probe"] = self._probe(photo, camera, table, resting, space, probe)
            # Wall time: with several CPU threads the per-batch stages are CPU times and sum to more (see _batched).
            wall_s = time.perf_counter() - t_start
        finally:
            if bar is not None:
                bar.close()

        tx, ty, tyaw, _ = np.array(top).T  # table frame: metres, metres, radians
        R, tr = model_to_camera(table, resting, tx, ty, tyaw)
        cands = [Candidate(*c, pose_matrix(R[n], tr[n])) for n, c in enumerate(top)]
        timings["total"] = wall_s
        return Result(
            best=cands[0],
            top_k=cands,
            n_candidates=len(space),
            n_scored=int(np.isfinite(scores).sum()),
            timings_s=timings,
            device=self.device,
            info={
                "weights": self.weights.source,
                "stride_px": cfg.stride,
                "alpha": cfg.alpha,
                "clusters": cfg.clusters,
                "seed": cfg.seed,
                "score": self.score_name,
                "search": self.search,
                "search_option": cfg.search,  # as asked: "auto" or the search itself
                **renderer_info,
                "conv": self.scorer.conv,
                "conv_option": cfg.conv,
                "image_scale": cfg.image_scale,
                "search_space": space.describe(),
                "evaluated": evaluated,  # candidates scored (rendered and compared)
                "batches": self._n_batches,
                "rays": self._n_rays,  # pixels ray-cast by kernel #1 (the rendered boxes' areas)
                # Batches scored at once; above 1 the per-batch stage timings are CPU seconds summed over threads.
                "threads": self.cpu_threads(),
                **extra,
            },
        )

    def _refine(self, photo, camera, table, resting, space: SearchSpace, top: list, timings: dict):
        """The best grid pose refined below the grid: the best of its cell at the fine resolution
        (perch_warp.refine), searched as the grid was (pruned or exhaustive: the same best). It replaces
        the first of top [(x_m, y_m, yaw_rad, score)]; the runners-up stay. Timed as one "refine" stage
        (wall time); its rays are counted apart from the grid search's."""
        cfg = self.config
        t = time.perf_counter()
        counters = (self._n_batches, self._n_rays, self._n_bound_rays)
        inner: dict[str, float] = {}
        x0, y0, yaw0, s0 = top[0]
        cell = cell_space(space, x0, y0, yaw0, cfg.refine_xy_m, cfg.refine_yaw_rad, cfg.refine_cells)
        best, scores, search = self._best_in(photo, camera, table, resting, cell, space.full_circle, inner)
        info = {
            "step_xy_m": cell.xy_step_m,
            "step_yaw_deg": math.degrees(cell.yaw_step_rad),
            "cell": cell.describe(),
            "search": search,
            "candidates": len(cell),
            "evaluated": int(np.isfinite(scores).sum()),
            "from": {"x_m": x0, "y_m": y0, "yaw_deg": math.degrees(yaw0), "score": s0},
            "score_gain": best[3] - s0,
            "rays": self._n_rays - counters[1],
        }
        self._n_batches, self._n_rays, self._n_bound_rays = counters  # the grid search's, as without refinement
        self._lap(timings, "refine", t)

        def same(c) -> bool:
            return abs(c[0] - best[0]) < 1e-9 and abs(c[1] - best[1]) < 1e-9 and abs(c[2] - best[2]) < 1e-9

        return [best, *(c for c in top[1:] if not same(c))], info

    def _pool(self) -> int:
        """Best grid candidates a search keeps: the top-k reported, or more to find distinct peaks among."""
        return peak_pool(self.config.top_k, self.config.refine_peaks if self.config.refine else 1)

    def _refine_peaks(self, photo, camera, table, resting, space: SearchSpace, top: list, timings: dict):
        """Engine._refine on each of the grid's best `refine_peaks` distinct peaks (perch_warp.peaks, cells
        that cannot overlap); the best refined pose first, then the others' refined poses, then the runners-up."""
        cfg = self.config
        if cfg.refine_peaks <= 1:
            return self._refine(photo, camera, table, resting, space, top, timings)
        reach = cfg.refine_cells
        idx = distinct_peaks(top, cfg.refine_peaks, 2 * reach * space.xy_step_m, 2 * reach * space.yaw_step_rad)
        refined = []
        for i in idx:
            rest = [c for j, c in enumerate(top) if j != i]
            out, info = self._refine(photo, camera, table, resting, space, [top[i], *rest], timings)
            refined.append((out[0], info))
        order = sorted(range(len(refined)), key=lambda n: -refined[n][0][3])  # stable: ties to the better grid peak
        best, info = refined[order[0]]
        info = {**info, "peaks": [{"from": r[1]["from"], "score": r[0][3]} for r in refined]}
        firsts = [refined[n][0] for n in order]
        seen = {tuple(top[i][:3]) for i in idx}
        return [*firsts, *(c for c in top if tuple(c[:3]) not in seen)], info

    def _best_in(self, photo, camera, table, resting, cell: SearchSpace, wrap: bool, timings: dict):
        """The best pose (x_m, y_m, yaw_rad, score) of a small space searched whole (pruned or exhaustive:
        the same best; after coarse-to-fine, the one "auto" picks for the device), its scores and the search."""
        search = self.search if self.search in ("exhaustive", "pruned") else _auto_search(self.device)
        if search == "pruned":
            scores, _ = self._pruned(photo, camera, table, resting, cell, timings)
        else:
            scores = self._score_poses(photo, camera, table, resting, _Poses.of_space(cell), timings)
        i = int(np.argmax(scores))  # the first of equal maxima
        (x_i,), (y_i,), (yaw_i,) = cell.at(np.array([i]))
        # A cell may reach below 0 on the full circle: the same poses as below 2π, reported there.
        yaw_i = float(yaw_i) % (2 * math.pi) if wrap else float(yaw_i)
        return (float(x_i), float(y_i), yaw_i, float(scores[i])), scores, search

    def _probe(self, photo, camera, table, resting, space: SearchSpace, pose: tuple[float, float, float]) -> dict:
        """The best of pose's cell at the refinement's resolution (Engine.estimate's `probe`); the search's
        counters are left as they were."""
        cfg = self.config
        counters = (self._n_batches, self._n_rays, self._n_bound_rays)
        everywhere = SearchSpace((-1e6, 1e6), (-1e6, 1e6), space.xy_step_m, FULL_CIRCLE, space.yaw_step_rad)
        x, y, yaw = (float(v) for v in pose)
        cell = cell_space(everywhere, x, y, yaw, cfg.refine_xy_m, cfg.refine_yaw_rad, cfg.refine_cells)
        (bx, by, byaw, score), scores, _ = self._best_in(photo, camera, table, resting, cell, True, {})
        self._n_batches, self._n_rays, self._n_bound_rays = counters
        return {"x_m": bx, "y_m": by, "yaw_rad": byaw, "score": score, "candidates": len(cell), "at": [x, y, yaw]}

    def score(
        self,
        image_rgb: np.ndarray,
        camera: Camera,
        table: Table,
        resting: RestingPose,
        x_m: np.ndarray,
        y_m: np.ndarray,
        yaw_rad: np.ndarray,
    ) -> np.ndarray:
        """Scores (N,) float64 of the given table-frame poses (metres, radians) in the photo; -inf where
        a pose shows no feature point. The photo's features and rarity are computed for this call."""
        timings: dict[str, float] = {}
        image_rgb, camera = self._begin(image_rgb, camera)
        self._pick_renderer(camera, table, resting, SearchSpace((0.0, 0.0), (0.0, 0.0)))
        photo = self._photo(image_rgb, camera, timings)
        x, y, yaw = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (x_m, y_m, yaw_rad))
        return self._score_poses(photo, camera, table, resting, _Poses.of_arrays(x, y, yaw), timings)

    def bounds_and_scores(
        self, image_rgb: np.ndarray, camera: Camera, table: Table, resting: RestingPose, space: SearchSpace
    ) -> dict[str, np.ndarray]:
        """Every candidate's silhouette bound and score (analysis of the pruned search; nothing pruned):
        arrays x_m, y_m, yaw_rad (table frame), bound, score; -inf where a candidate shows no feature point."""
        timings: dict[str, float] = {}
        image_rgb, camera = self._begin(image_rgb, camera)
        photo = self._photo(image_rgb, camera, timings)
        x, y, yaw = space.candidates()
        R, tr, boxes, gboxes, live = self._candidates(camera, table, resting, x, y, yaw, timings)
        bounds, scores = np.full(len(x), -np.inf), np.full(len(x), -np.inf)
        self._bound_some(photo, camera, R, tr, boxes, gboxes, live, bounds, timings)
        self._score_some(photo, camera, R, tr, boxes, gboxes, live, scores, timings)
        return {"x_m": x, "y_m": y, "yaw_rad": yaw, "bound": bounds, "score": scores}

    def _pick_renderer(self, camera: Camera, table: Table, resting: RestingPose, space: SearchSpace) -> dict:
        """Set the renderer for this search (--renderer auto: render.auto_renderer, from the median
        box of up to 256 of the space's candidates, drawn with a fixed seed); what ran, for the result."""
        info: dict = {"renderer_option": self.config.renderer, "mesh_faces": int(len(self.mesh.faces))}
        if self.config.renderer == "auto":
            median = 0.0
            if wp.get_device(self.device).is_cpu:
                R, t = model_to_camera(table, resting, *space.sample(256, seed=0))
                boxes = self.boxes(camera, R, t)
                shown = (boxes[:, 2] > 0) & (boxes[:, 3] > 0)  # -1: behind the camera, 0: outside the image
                areas = boxes[shown, 2].astype(np.int64) * boxes[shown, 3]
                median = float(np.median(areas)) if len(areas) else 0.0
                info["median_box_px"] = median
            self.renderer.use(auto_renderer(self.device, info["mesh_faces"], median))
        info["renderer"] = self.renderer.method
        info["cull_back_faces"] = self.renderer.cull_back_faces  # raster on a closed mesh only
        return info

    def _begin(self, image_rgb: np.ndarray, camera: Camera) -> tuple[np.ndarray, Camera]:
        """Zero the per-search counters; the photo and camera the search runs on (image_scale applied)."""
        self._n_batches = self._n_rays = self._n_bound_rays = 0
        if self.config.image_scale != 1.0:
            return _rescale(check_rgb(image_rgb), camera, self.config.image_scale)
        return image_rgb, camera

    def _photo(self, image_rgb: np.ndarray, camera: Camera, timings: dict) -> _Photo:
        """The photo's feature map, norms and rarity, on the device (once per photo)."""
        cfg = self.config
        image_rgb = check_rgb(image_rgb)
        if image_rgb.shape[:2] != (camera.height, camera.width):
            raise PerchError(
                f"image is {image_rgb.shape[1]}x{image_rgb.shape[0]} but the camera is {camera.width}x{camera.height}"
            )
        ks = self.weights.kernel_size
        rows, cols = grid_shape(camera.width, camera.height, ks, cfg.stride)
        if rows < 1 or cols < 1:
            raise PerchError(f"image {camera.width}x{camera.height} is smaller than the {ks}x{ks} feature window")
        t = time.perf_counter()
        image = self.scorer.image_to_device(image_rgb)
        obs = self.scorer.observed_features(image)
        t = self._lap(timings, "photo_features", t)
        feats = obs.numpy().reshape(rows * cols, -1)
        terms = self.terms
        rar, labels = rarity_and_labels(feats, cfg.clusters, cfg.seed, terms.rarity, terms.inits)
        offset = background_offset(feats, labels, rar, terms.background)
        ceiling = (rar - offset).reshape(rows, cols)
        norms = np.linalg.norm(feats.astype(np.float64), axis=1).reshape(rows, cols).astype(np.float32)
        with wp.ScopedDevice(self.device):
            gain = wp.array(rar.reshape(rows, cols), dtype=float)
            pw = point_weights(gain, wp.array(offset.reshape(rows, cols), dtype=float))
            # The thesis's ceiling is the rarity itself: the same array, so its bounds stay bit for bit.
            ceil = gain if terms.background == 0.0 else wp.array(ceiling, dtype=float)
            photo = _Photo(image, obs, wp.array(norms, dtype=float), pw, ceil, rows, cols)
        self._lap(timings, "rarity", t)
        return photo

    def _lap(self, timings: dict, stage: str, t0: float) -> float:
        wp.synchronize_device(self.device)
        t1 = time.perf_counter()
        timings[stage] = timings.get(stage, 0.0) + (t1 - t0)
        return t1

    def _candidates(self, camera, table, resting, x, y, yaw, timings: dict):
        """Poses (model-to-camera R, t in metres), pixel boxes, feature-grid boxes of candidates
        (x_m, y_m, yaw_rad arrays) and the indices of those that show at least one feature point."""
        cfg = self.config
        t = time.perf_counter()
        R, tr = model_to_camera(table, resting, x, y, yaw)
        boxes = self.boxes(camera, R, tr)  # = project_boxes(camera, self.hull_m, R, tr), on the device
        if np.any(boxes[:, 2] < 0):
            n_bad = int((boxes[:, 2] < 0).sum())
            raise PerchError(
                f"{n_bad} of {len(boxes)} candidate poses set up together are behind or within {MIN_DEPTH_M} m "
                "of the camera: check the table frame and the search ranges"
            )
        gboxes = grid_boxes(boxes, self.weights.kernel_size, cfg.stride)
        live = np.flatnonzero(gboxes[:, 2] * gboxes[:, 3] > 0)
        self._lap(timings, "candidates", t)
        return R, tr, boxes, gboxes, live

    def _setup(self, camera, table, resting, poses: _Poses, idx: np.ndarray, timings: dict):
        """Engine._candidates of candidates idx of poses (a chunk: the arrays are idx's, in its order)."""
        return self._candidates(camera, table, resting, *poses.at(idx), timings)

    def _score_poses(self, photo, camera, table, resting, poses: _Poses, timings: dict, bar=None) -> np.ndarray:
        """Score of each candidate of poses, set up a chunk at a time; -inf where it shows no feature point
        (those count as done on the progress bar at once)."""
        scores = np.full(poses.n, -np.inf)
        if bar is not None:
            bar.total += poses.n
            bar.refresh()
        for idx in poses.chunks():
            R, tr, boxes, gboxes, live = self._setup(camera, table, resting, poses, idx, timings)
            if bar is not None:
                bar.update(len(idx) - len(live))
            part = np.full(len(idx), -np.inf)
            self._score_some(photo, camera, R, tr, boxes, gboxes, live, part, timings, bar)
            scores[idx] = part
        return scores

    def _score_some(self, photo, camera, R, tr, boxes, gboxes, idx, scores, timings: dict, bar=None) -> None:
        """scores[idx] = the scores of candidates idx (render, features, top-α), in batches."""
        sizes = boxes[idx, 2].astype(np.int64) * boxes[idx, 3]
        self._n_rays += int(sizes.sum())
        work = functools.partial(self._score_batch, photo, camera, R, tr, boxes, gboxes)
        self._batched(work, idx, sizes, scores, timings, bar)

    def _bound_some(self, photo, camera, R, tr, boxes, gboxes, idx, bounds, timings: dict) -> None:
        """bounds[idx] = the silhouette bounds of candidates idx (perch_warp.bound), in batches."""
        sizes = gboxes[idx, 2].astype(np.int64) * gboxes[idx, 3]  # one ray per feature point
        self._n_bound_rays += int(sizes.sum())
        work = functools.partial(self._bound_batch, photo, camera, R, tr, boxes, gboxes)
        self._batched(work, idx, sizes, bounds, timings, None)

    def _batched(self, work, idx: np.ndarray, sizes: np.ndarray, out: np.ndarray, timings: dict, bar) -> None:
        """out[b] = work(b)[0] for batches b of idx (their sizes, in rays, within the device's budget),
        on a thread pool on the CPU; work's stage seconds are added to timings."""
        budget = self._budget()
        n_rays = int(sizes.sum())
        threads = self.cpu_threads()
        if threads > 1:
            # Smaller batches so that every thread has some and those in flight together hold
            # about one budget's pixels; not below 64 Ki pixels (launch overhead) unless the budget is.
            budget = max(min(budget, 1 << 16), min(budget // threads, -(-n_rays // (2 * threads))))
        batches = [idx[lo:hi] for lo, hi in _split_by_budget(sizes, budget)]
        self._n_batches += len(batches)
        threads = min(threads, len(batches))

        def done(b: np.ndarray, values: np.ndarray, laps: dict[str, float]) -> None:
            out[b] = values  # by candidate index: the order batches finish in does not matter
            for stage, sec in laps.items():
                timings[stage] = timings.get(stage, 0.0) + sec
            if bar is not None:
                bar.update(len(b))

        if threads <= 1:
            with self.scorer.conv_settings():
                for b in batches:
                    done(b, *work(b))
            return
        # Each batch on a pool thread, its arrays its own (the renderer and scorer allocate per call
        # and keep no per-call state). A stage's time is then the sum over threads of its per-batch
        # times, i.e. CPU time, which can exceed the wall time; "total" stays wall time.
        with (
            self.scorer.conv_settings(),
            _default_device(self.device),
            ThreadPoolExecutor(threads, thread_name_prefix="perch-score") as pool,
        ):
            futures = {pool.submit(work, b): b for b in batches}
            try:
                for f in as_completed(futures):
                    done(futures[f], *f.result())
            except BaseException:
                for f in futures:
                    f.cancel()
                raise

    def _budget(self) -> int:
        """Rays (pixels or feature points) per batch: the config's, else sized to the device."""
        return self.config.batch_pixels or _batch_pixels(self.device)

    def cpu_threads(self) -> int:
        """Threads scoring batches at once: 1 on a GPU (one stream), else the config's or one per core."""
        if not wp.get_device(self.device).is_cpu:
            return 1
        if self.config.cpu_threads is not None:
            return self.config.cpu_threads
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1

    def _score_batch(self, photo, camera, R, tr, boxes, gboxes, idx) -> tuple[np.ndarray, dict[str, float]]:
        """Candidates `idx`: render (kernel #1) -> features x similarity x rarity (kernel #2) ->
        top-α mean; their scores on the host and the seconds each stage took."""
        laps: dict[str, float] = {}
        t = time.perf_counter()
        batch = self.renderer.render(camera, R[idx], tr[idx], boxes[idx])
        t = self._lap(laps, "render", t)
        vals, pt_off = self.scorer.score_points(photo.image, batch, gboxes[idx], photo.obs, photo.norm, photo.weights)
        t = self._lap(laps, "features_score", t)
        # The same kernel on every device, so CPU and GPU runs take the same path to a score.
        batch_scores, _ = top_alpha_mean_device(vals, pt_off, self.config.alpha, self.terms.shrink)
        t = self._lap(laps, "reduction", t)
        out = batch_scores.numpy()  # one float per candidate, not every feature point
        self._lap(laps, "transfer", t)
        return out, laps

    def _bound_batch(self, photo, camera, R, tr, boxes, gboxes, idx) -> tuple[np.ndarray, dict[str, float]]:
        """Candidates `idx`: upper bounds of their scores from their silhouettes, and the seconds taken."""
        laps: dict[str, float] = {}
        t = time.perf_counter()
        out = silhouette_bounds(
            self.renderer,
            camera,
            R[idx],
            tr[idx],
            boxes[idx],
            gboxes[idx],
            photo.ceiling,
            self.weights.kernel_size,
            self.config.stride,
            self.config.alpha,
            self.terms.shrink,
        )
        self._lap(laps, "bound", t)
        return out, laps

    def _pruned(self, photo, camera, table, resting, space: SearchSpace, timings: dict, bar=None):
        """Every grid candidate bounded by its silhouette (perch_warp.bound), then scored best bound
        first until no remaining bound reaches the k-th best score: the exhaustive search's top-k,
        scoring only the candidates that could be in it. Returns the scores (-inf where not scored)
        in candidates()'s order and what the search did."""
        scores = np.full(len(space), -np.inf)
        k = self._pool()

        def kth_best(scored: np.ndarray) -> float:
            return _kth_largest(scores[scored], k)

        scored, rounds, _, bounded = self._best_first(
            photo, camera, table, resting, _Poses.of_space(space), scores, timings, kth_best, bar
        )
        info = {
            "bounded": bounded,
            "scored": len(scored),
            "rounds": rounds,
            "bound_rays": self._n_bound_rays,
            "k": k,  # the rank whose score a bound had to reach
        }
        return scores, info

    def _best_first(self, photo, camera, table, resting, poses: _Poses, scores, timings, kth_best, bar=None):
        """Bound the candidates of poses (those showing feature points), then score them best bound
        first, a round of batches at a time, until no remaining bound reaches kth_best(indices scored
        so far). Returns the indices scored, the number of rounds, the bounds (-inf where not bounded)
        and the number bounded. scores[i] stays -inf for the others: those without feature points
        (whose score is -inf) and those ruled out (whose score is below the final threshold). Poses
        and boxes are set up a chunk at a time, for the bounds and again for each round; only a
        bound and a box size per candidate are kept. The progress bar counts a candidate as done
        once it is scored or can no longer be (its bound below the threshold so far, or no feature
        points), so that its rate and time left follow where the search will really end."""
        bounds = np.full(poses.n, -np.inf)
        box_px = np.zeros(poses.n, dtype=np.int64)
        n_live = 0
        for idx in poses.chunks():
            R, tr, boxes, gboxes, live = self._setup(camera, table, resting, poses, idx, timings)
            box_px[idx] = boxes[:, 2].astype(np.int64) * boxes[:, 3]
            part = np.full(len(idx), -np.inf)
            self._bound_some(photo, camera, R, tr, boxes, gboxes, live, part, timings)
            bounds[idx] = part
            n_live += len(live)
        # A candidate without feature points scores -inf whatever it shows: never worth scoring.
        order = np.argsort(-bounds, kind="stable")
        order = order[np.isfinite(bounds[order])]
        ranked = bounds[order]
        if bar is not None:
            bar.total += n_live
            bar.refresh()
        reported = 0

        def report(done: int) -> None:
            nonlocal reported
            if bar is not None and done > reported:
                bar.update(done - reported)
                reported = done

        # A round: about one budget of rays per thread, so that the first rounds set the threshold
        # early and each later one stops as soon as the bounds fall below it.
        per_round = self._budget() * self.cpu_threads()
        threshold = kth_best(order[:0])
        pos = 0
        rounds = 0
        while pos < len(order):
            end = min(next_to_score(ranked, pos, threshold), pos + SETUP_CHUNK)
            if end <= pos:
                break
            sizes = box_px[order[pos:end]]
            end = pos + max(1, int(np.searchsorted(np.cumsum(sizes), per_round, side="right")))
            idx = order[pos:end]
            R, tr, boxes, gboxes, _ = self._setup(camera, table, resting, poses, idx, timings)
            part = np.full(len(idx), -np.inf)
            self._score_some(photo, camera, R, tr, boxes, gboxes, np.arange(len(idx)), part, timings, None)
            scores[idx] = part
            pos = end
            rounds += 1
            threshold = kth_best(order[:pos])
            report(n_live - (next_to_score(ranked, pos, threshold) - pos))
        report(n_live)
        return order[:pos], rounds, bounds, n_live

    def _coarse_to_fine(self, photo, camera, table, resting, space: SearchSpace, timings: dict, bar=None):
        """Pyramid search on the space's own grid: a coarse lattice, then around the best `beam`
        candidates ever finer lattices down to the grid step, then hill-climbing on the grid
        until the best `beam` stop changing. Every grid point is scored at most once."""
        cfg = self.config
        nx, ny, nk = (len(a) for a in space.axes())
        wrap = space.full_circle
        f_xy = max(1, round(cfg.coarse_xy_m / space.xy_step_m))
        f_yaw = max(1, round(cfg.coarse_yaw_rad / space.yaw_step_rad))
        steps = [(f_xy, f_yaw)]
        while steps[-1] != (1, 1):
            steps.append((max(1, steps[-1][0] // 2), max(1, steps[-1][1] // 2)))
        memo: dict[int, float] = {}
        # Grid points whose silhouette bound fell below the beam's threshold: they can never enter
        # the beam (the threshold only rises as memo grows), so they are neither scored nor asked again.
        ruled_out: set[int] = set()
        k_beam = max(cfg.beam, cfg.top_k)

        def run(ijk: np.ndarray) -> None:
            i, j, k = ijk.T
            k = k % nk if wrap else k
            ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny) & (k >= 0) & (k < nk)
            flat = np.unique((i[ok] * ny + j[ok]) * nk + k[ok])
            flat = np.array([f for f in flat.tolist() if f not in memo and f not in ruled_out], dtype=np.int64)
            if len(flat) == 0:
                return
            poses = _Poses.of_arrays(*space.at(flat))
            if not cfg.pyramid_bounds:
                sc = self._score_poses(photo, camera, table, resting, poses, timings, bar)
                memo.update(zip(flat.tolist(), sc.tolist(), strict=True))
                return
            sc = np.full(len(flat), -np.inf)
            known = np.fromiter(memo.values(), dtype=np.float64, count=len(memo))

            def kth_best(scored: np.ndarray) -> float:
                return _kth_largest(np.concatenate([known, sc[scored]]), k_beam)

            scored, _, bounds, _ = self._best_first(photo, camera, table, resting, poses, sc, timings, kth_best, bar)
            # Memoised: the scored, and those whose score is -inf because no feature point shows (as
            # without bounds). Ruled out: a finite bound below the threshold, so a score below it too.
            dropped = np.isfinite(bounds)
            dropped[scored] = False
            memo.update(zip(flat[~dropped].tolist(), sc[~dropped].tolist(), strict=True))
            ruled_out.update(flat[dropped].tolist())

        def best() -> np.ndarray:
            flat = np.fromiter(memo.keys(), dtype=np.int64, count=len(memo))
            sc = np.fromiter(memo.values(), dtype=np.float64, count=len(memo))
            top = flat[np.lexsort((flat, -sc))[: cfg.beam]]
            ii, rest = np.divmod(top, ny * nk)
            jj, kk = np.divmod(rest, nk)
            return np.stack([ii, jj, kk], -1)

        def around(centres: np.ndarray, reach: tuple[int, int], step: tuple[int, int]) -> np.ndarray:
            dxy = np.arange(-reach[0], reach[0] + 1, step[0])
            dk = np.arange(-reach[1], reach[1] + 1, step[1])
            D = np.stack(np.meshgrid(dxy, dxy, dk, indexing="ij"), -1).reshape(-1, 3)
            return (centres[:, None, :] + D[None]).reshape(-1, 3)

        def lattice(n: int, f: int, closed: bool) -> np.ndarray:
            a = np.arange(0, n, f)
            return np.union1d(a, [n - 1]) if closed else a

        li, lj, lk = lattice(nx, f_xy, True), lattice(ny, f_xy, True), lattice(nk, f_yaw, not wrap)
        run(np.stack(np.meshgrid(li, lj, lk, indexing="ij"), -1).reshape(-1, 3))
        levels = [
            {
                "step_xy_m": f_xy * space.xy_step_m,
                "step_yaw_deg": math.degrees(f_yaw * space.yaw_step_rad),
                "evaluated": len(memo),
            }
        ]
        for prev, step in zip(steps, steps[1:], strict=False):
            n0 = len(memo)
            run(around(best(), prev, step))
            levels.append(
                {
                    "step_xy_m": step[0] * space.xy_step_m,
                    "step_yaw_deg": math.degrees(step[1] * space.yaw_step_rad),
                    "evaluated": len(memo) - n0,
                }
            )
        n0 = len(memo)
        for _ in range(cfg.max_polish):
            before = len(memo)
            run(around(best(), (1, 1), (1, 1)))
            if len(memo) == before:
                break
        levels.append({"polish_evaluated": len(memo) - n0})

        flat = np.fromiter(memo.keys(), dtype=np.int64, count=len(memo))
        order = np.argsort(flat)
        sc = np.fromiter(memo.values(), dtype=np.float64, count=len(memo))[order]
        return flat[order], sc, levels  # flat indices into candidates()'s order, ascending


def _auto_search(device: str) -> str:
    """What --search auto runs: pruned on the CPU (measured faster there), exhaustive on a GPU (not measured)."""
    return "pruned" if wp.get_device(device).is_cpu else "exhaustive"


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


def _rescale(image_rgb: np.ndarray, camera: Camera, factor: float) -> tuple[np.ndarray, Camera]:
    """The photo resized (area filter) and its camera with it; poses stay in metres, so results do not change frame."""
    from PIL import Image

    if image_rgb.shape[:2] != (camera.height, camera.width):
        raise PerchError(
            f"image is {image_rgb.shape[1]}x{image_rgb.shape[0]} but the camera is {camera.width}x{camera.height}"
        )
    small = camera.scaled(factor)
    img = Image.fromarray(image_rgb).resize((small.width, small.height), Image.Resampling.BOX)
    return np.asarray(img), small


def _top_indices(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k largest scores, best first, ties to the lower index: the first k of a
    stable argsort of -scores, without sorting the whole space."""
    if len(scores) > k:
        kth = np.partition(scores, len(scores) - k)[len(scores) - k]
        idx = np.flatnonzero(scores >= kth)
    else:
        idx = np.arange(len(scores))
    return idx[np.argsort(-scores[idx], kind="stable")][:k]


def _kth_largest(values: np.ndarray, k: int) -> float:
    """The k-th largest of values; -inf when there are fewer than k (nothing can be ruled out yet)."""
    n = len(values)
    return float(np.partition(values, n - k)[n - k]) if 0 < k <= n else -np.inf


def _split_by_budget(sizes: np.ndarray, budget: int) -> list[tuple[int, int]]:
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
