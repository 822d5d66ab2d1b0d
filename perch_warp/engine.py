"""The search engine: build once per mesh (and weights, device), call once per photo.

Stages: photo features -> rarity (k-means) -> candidate poses and their boxes
(kernels/boxes.py) -> per batch: render (kernel #1) -> features x similarity x
rarity (kernel #2) -> top-α mean (kernels/reduce.py) -> best pose. Only boxes and
one score per candidate come back to the host.

Engine is a façade: it builds the renderer and scorer once per mesh, a scoring service per photo
(perch_warp.search.scoring), runs the search chosen by name (perch_warp.search) and the
refinement (search.refine), and assembles the Result.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import tqdm
import warp as wp
from PIL import Image

from . import search as searches
from .camera import Camera
from .confidence import Confidence, grid_confidence, yaw_differs
from .config import SEARCHES, EngineConfig
from .errors import PerchError
from .features import FeatureWeights, smoothed
from .hidden import DEFAULT_BETA, HiddenPoints, hidden_points, occluder_map
from .image import check_rgb
from .mesh import ObjectMesh
from .peaks import top_location_candidates
from .render import BoxProjector, DeviceMesh, Renderer, auto_renderer, make_renderer
from .resting import Rest
from .result import Candidate, RestingChoice, Result, SearchInfo
from .score import FeatureScorer, auto_conv, grid_shape
from .score_map import ScoreMap, knowledge, score_map, score_map_over_rests
from .score_terms import parse_score
from .search import rests as over_rests
from .search.base import Outcome, top_indices
from .search.known import KnownScores
from .search.refine import probe as probe_cell
from .search.refine import refine_peaks
from .search.scoring import Backends, Photo, ScoringService, cpu_threads, photo_on_device
from .search_space import SearchSpace
from .table import RestingPose, Table, model_to_camera, pose_matrix

__all__ = ["SEARCHES", "Engine", "EngineConfig", "default_device"]


class RendererChoice(NamedTuple):
    """The renderer a search uses and, where --renderer auto's CPU rule ran, the median candidate box
    (pixels) it compared the mesh's faces with."""

    renderer: Renderer
    median_box_px: float | None


def default_device() -> str:
    """A CUDA GPU when Warp sees one, else the CPU (callers report which)."""
    return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"


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
        self.score_name, self.terms = parse_score(self.config.score)  # perch_warp.score_terms
        raw = self.terms.raw_conv1_terms()
        if raw and self.config.relu:
            # One message for every such term, so that dropping one does not only reveal the next.
            it = "it" if len(raw) == 1 else "them"
            raise PerchError(
                f"score {self.config.score!r} uses {' and '.join(raw)}, which need{'s' if it == 'it' else ''} raw "
                f"conv1: drop --relu, or use a score without {it} (e.g. --score grid-tolerant)"
            )
        # Uploaded once, shared by both renderers; the score's texture term says how they read the texture.
        self.device_mesh = DeviceMesh(mesh, self.device, self.terms.texture)
        self._renderers: dict[str, Renderer] = {}
        self.renderer_for(self.default_renderer)  # built now: BVH construction is not a search stage's
        conv = self.config.conv if self.config.conv != "auto" else auto_conv(self.device, self.terms.centre)
        if self.terms.centre > 0.0 and conv != "torch":
            raise PerchError(
                f"score {self.config.score!r} centres each candidate's features (centre={self.terms.centre}), "
                "which kernel #2's torch form alone does: use --conv torch, or a score without it "
                "(e.g. --score grid-tolerant)"
            )
        self.scorer = FeatureScorer(
            smoothed(weights, self.terms.smooth),
            self.device,
            self.config.stride,
            self.config.relu,
            conv,
            surround=self.terms.surround,
            light=self.terms.light,
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
        return self.config.search if self.config.search != "auto" else searches.auto_search(self.device)

    @property
    def default_renderer(self) -> str:
        """The form of kernel #1 this engine renders with outside a search: the configured one, bvh for auto."""
        return "bvh" if self.config.renderer == "auto" else self.config.renderer

    @property
    def renderer(self) -> Renderer:
        """The renderer of `default_renderer` (a search may pick the other form: Result.info.renderer)."""
        return self.renderer_for(self.default_renderer)

    def renderer_for(self, method: str) -> Renderer:
        """The renderer called `method` ("bvh" or "raster") for this mesh, built on first use and kept."""
        if method not in self._renderers:
            self._renderers[method] = make_renderer(method, self.device_mesh)
        return self._renderers[method]

    def cpu_threads(self) -> int:
        """Threads scoring batches at once: 1 on a GPU (one stream), else the config's or one per core."""
        return cpu_threads(self.device, self.config.cpu_threads)

    def render(self, camera: Camera, T_m2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full-image rendering of one pose: RGB float32 (H, W, 3) in [0, 1], mask bool (H, W)."""
        T = np.asarray(T_m2c, dtype=np.float64)
        return self.renderer.render_image(camera, T[:3, :3], T[:3, 3])

    def scoring(
        self,
        image_rgb: np.ndarray,
        camera: Camera,
        table: Table,
        resting: RestingPose,
        space: SearchSpace | None = None,
        timings: dict | None = None,
        bar=None,
    ) -> ScoringService:
        """The scoring service for one photo (perch_warp.search.scoring): its features and rarity computed,
        image_scale applied, the renderer chosen for `space` (--renderer auto; a point space by default)."""
        timings = {} if timings is None else timings
        image_rgb, camera = self._scaled(image_rgb, camera)
        choice = self._pick_renderer(camera, table, resting, space or SearchSpace((0.0, 0.0), (0.0, 0.0)))
        return self._service(image_rgb, camera, table, resting, choice.renderer, timings, bar)

    def photo(self, image_rgb: np.ndarray, camera: Camera, timings: dict | None = None) -> Photo:
        """The photo's features and rarity on the device (image_scale applied), to search several objects
        in it with `estimate(..., photo=)`: engines with the same weights, device and method settings
        (EngineConfig) may share it; the mesh plays no part in it."""
        image_rgb, camera = self._scaled(image_rgb, camera)
        return photo_on_device(
            self._backends(), self.config, self.terms, image_rgb, camera, {} if timings is None else timings
        )

    def hidden_by(
        self, camera: Camera, placed: Sequence[tuple[Engine, np.ndarray]], beta: float = DEFAULT_BETA
    ) -> HiddenPoints:
        """What the objects `placed` hide of this engine's object in a photo taken by `camera` (before
        image_scale): each (the engine of its mesh, its model-to-camera pose T (4, 4), metres) rendered and
        kept by its model origin's distance from the camera, as perch_warp.hidden's occluder map on the
        feature grid this engine scores; pass it to `estimate(..., hidden=)`."""
        cam = camera.scaled(self.config.image_scale) if self.config.image_scale != 1.0 else camera
        rows, cols = grid_shape(cam.width, cam.height, self.weights.kernel_size, self.config.stride)
        silhouettes = []
        for engine, T in placed:
            T = np.asarray(T, dtype=np.float64)
            silhouettes.append((engine.render(cam, T)[1], float(np.linalg.norm(T[:3, 3]))))
        near = occluder_map(silhouettes, rows, cols, self.weights.kernel_size, self.config.stride)
        return hidden_points(near, beta, len(placed), self.device)

    def _backends(self) -> Backends:
        return Backends(self.scorer, self.boxes, self.weights, self.device)

    def _service(
        self, image_rgb, camera, table, resting, renderer: Renderer, timings: dict, bar, photo: Photo | None = None,
        hidden: HiddenPoints | None = None, known: KnownScores | None = None,
    ) -> ScoringService:  # fmt: skip
        backends = self._backends()
        if photo is None:
            photo = photo_on_device(backends, self.config, self.terms, image_rgb, camera, timings)
        args = (photo, camera, table, resting, renderer, timings, bar, hidden, known)
        return ScoringService(backends, self.config, self.terms, *args)

    def estimate(
        self,
        image_rgb: np.ndarray,
        camera: Camera,
        table: Table,
        resting: RestingPose | Sequence[Rest],
        space: SearchSpace,
        progress: bool = False,
        probe: tuple[float, float, float] | None = None,
        probe_resting: RestingPose | None = None,
        photo: Photo | None = None,
        hidden: HiddenPoints | None = None,
        known: KnownScores | None = None,
    ) -> Result:
        """Best (x, y, yaw) of the object in the photo; see the module doc for the stages.

        `resting`: one RestingPose, or several resting poses (perch_warp.resting.Rest, e.g. the mesh's
        stable poses) searched together (search/rests.py): the best (pose, x, y, yaw), the winner in
        Result.resting. `probe` (x_m, y_m, yaw_rad, table frame), for analysis only: after the search,
        the best pose and score within that pose's cell (one grid step either side at the refinement's
        resolution, not cut to the space) on the same photo, under `probe_resting` (default: the
        winning resting pose), in info.extra["probe"]; it never changes the answer. `photo`: this photo's
        features and rarity from `Engine.photo` (several objects in one photo), else computed here.
        `hidden`: what other objects hide in this photo (perch_warp.hidden, on the photo's grid after
        image_scale: `Engine.hidden_by`), left out of every score and bound; recorded in info.extra["hidden"].
        `known`: this object's plain scores and bounds in this photo (`photo` must be given) kept by an
        earlier search (search/known.py): taken where no point can be hidden instead of computed, the
        same values bit for bit; this search's plain values are kept there in turn. How many:
        info.extra["known"]."""
        if known is not None and photo is None:
            raise PerchError("known scores need the photo they were scored on: pass photo= (Engine.photo)")
        if not isinstance(resting, RestingPose):
            rests = list(resting)
            return self._estimate_rests(
                image_rgb, camera, table, rests, space, progress, probe, probe_resting, photo, hidden, known
            )
        timings: dict[str, float] = {}
        image_rgb, camera = self._scaled(image_rgb, camera)
        choice = self._pick_renderer(camera, table, resting, space)
        bar = _bar(progress, f"search on {self.device}")
        t_start = time.perf_counter()
        try:
            service = self._service(
                image_rgb, camera, table, resting, choice.renderer, timings, bar, photo, hidden, known
            )
            before = None if known is None else known.to_dict()
            out, top = self._search(service, space)
            assessed = self._assess(service, space, out, top[0][:3], resting)
            if known is not None:
                out.extra["known"] = _counted(known, before)
            # Wall time: with several CPU threads the per-batch stages are CPU times and sum to more.
            wall_s = time.perf_counter() - t_start
            if probe is not None:  # a diagnostic: timed apart, not part of the search's total
                t_probe = time.perf_counter()
                # Scored apart from the known scores, so the diagnostic never speeds a later search.
                service = dataclasses.replace(service, known=None)
                out.extra["probe"] = probe_cell(service, space, probe, self.search)
                timings["probe"] = time.perf_counter() - t_probe
        finally:
            if bar is not None:
                bar.close()
        timings["total"] = wall_s
        if hidden is not None:
            out.extra["hidden"] = hidden.to_dict()
        return self._result(table, resting, space, out, top, timings, choice, assessed)

    def _search(self, service: ScoringService, space: SearchSpace) -> tuple[Outcome, list]:
        """The configured search's outcome and its top-k [(x_m, y_m, yaw_rad, score)], refined."""
        out = searches.get(self.search)(service, space)
        scores = out.scores
        if not np.isfinite(scores).any():
            raise PerchError(f"the search grid projects outside the image ({space.describe()})")
        # Stable order: ties go to the earlier candidate, so results are reproducible.
        cfg = self.config
        if cfg.refine and cfg.refine_peaks > 1:  # the best candidate of each of the best locations
            flat = np.arange(len(scores)) if out.flat is None else out.flat
            order = top_location_candidates(flat, scores, len(space.axes()[2]), cfg.pool)
        else:
            order = top_indices(scores, cfg.top_k)
        x, y, yaw = space.at(order if out.flat is None else out.flat[order])
        top = [(float(x[n]), float(y[n]), float(yaw[n]), float(scores[i])) for n, i in enumerate(order)]
        if self.config.refine:
            top, out.extra["refine"] = refine_peaks(service, space, top, self.search)
        return out, top[: self.config.top_k]

    def _assess(
        self, service: ScoringService, space: SearchSpace, out: Outcome, answer, resting: RestingPose,
        over: list[Outcome] | None = None,
    ):  # fmt: skip
        """(ScoreMap, Confidence) of the answer (x_m, y_m, yaw_rad): perch_warp.score_map and .confidence,
        timed as one "confidence" stage; after the pruned search, the left-out candidates that could
        change the margin are scored (on a quiet service: not the search's stages). `over`: every resting
        pose's outcome (`out` among them), for a heat map of the best over them all; the confidence stays
        over `out`'s grid."""
        t = time.perf_counter()
        k = knowledge(out, space, self.search)
        quiet = service.quiet()

        def score_fn(flat: np.ndarray) -> np.ndarray:
            return quiet.score(space.at(flat))

        def differs(offsets: np.ndarray) -> np.ndarray:
            return yaw_differs(self.mesh.vertices_m, resting.R_rest, offsets)

        conf = grid_confidence(k, space, answer, differs, score_fn if out.bounds is not None else None)
        if over is None:
            smap = score_map(k, space)
        else:
            smap, _ = score_map_over_rests([k if o is out else knowledge(o, space, self.search) for o in over], space)
        service.lap("confidence", t)
        return smap, conf

    def _result(
        self, table, resting, space: SearchSpace, out: Outcome, top: list, timings, choice,
        assessed: tuple[ScoreMap, Confidence],
    ) -> Result:  # fmt: skip
        tx, ty, tyaw, _ = np.array(top).T  # table frame: metres, metres, radians
        R, tr = model_to_camera(table, resting, tx, ty, tyaw)
        cands = [Candidate(*c, pose_matrix(R[n], tr[n])) for n, c in enumerate(top)]
        return self._result_of(cands, len(space), out, timings, choice, space, assessed)

    def _result_of(
        self, cands: list, n: int, out: Outcome, timings, choice, space, assessed: tuple[ScoreMap, Confidence]
    ) -> Result:
        """The Result of a search over n candidates (space: its x, y, yaw grid; several resting poses: n is
        len(space) times their number)."""
        cfg = self.config
        info = SearchInfo(
            weights=self.weights.source,
            stride_px=cfg.stride,
            alpha=cfg.alpha,
            clusters=cfg.clusters,
            seed=cfg.seed,
            score=self.score_name,
            search=self.search,
            search_option=cfg.search,
            renderer_option=cfg.renderer,
            mesh_faces=int(len(self.mesh.faces)),
            median_box_px=choice.median_box_px,
            renderer=choice.renderer.name,
            cull_back_faces=choice.renderer.cull_back_faces,
            conv=self.scorer.conv,
            conv_option=cfg.conv,
            image_scale=cfg.image_scale,
            search_space=space.describe(),
            evaluated=out.evaluated,
            batches=out.stats.batches,
            rays=out.stats.rays,
            threads=self.cpu_threads(),
            extra=out.extra,
        )
        n_scored = int(np.isfinite(out.scores).sum())
        smap, conf = assessed
        return Result(cands[0], cands, n, n_scored, timings, self.device, info, confidence=conf, heatmap=smap)

    def _estimate_rests(
        self, image_rgb, camera, table, rests: list[Rest], space, progress, probe, probe_resting, photo, hidden, known
    ):
        """`estimate` over several resting poses (search/rests.py), on one scoring service."""
        if not rests:
            raise PerchError("no resting pose to search (an empty list)")
        timings: dict[str, float] = {}
        image_rgb, camera = self._scaled(image_rgb, camera)
        # The renderer is chosen from the first (most probable) pose's boxes: it changes speed, not images.
        choice = self._pick_renderer(camera, table, rests[0].pose, space)
        bar = _bar(progress, f"search on {self.device}")
        t_start = time.perf_counter()
        try:
            first = self._service(
                image_rgb, camera, table, rests[0].pose, choice.renderer, timings, bar, photo, hidden, known
            )
            before = None if known is None else known.to_dict()
            services = [over_rests.with_rest(first, r.pose) for r in rests]
            outs = over_rests.search_all(services, space, self.search, [r.label for r in rests])
            top = over_rests.joint_top(outs, space, self.config)
            if not top:
                raise PerchError(f"the search grid projects outside the image ({space.describe()})")
            extra: dict = {} if hidden is None else {"hidden": hidden.to_dict()}
            if self.config.refine:
                top, extra["refine"] = over_rests.refine_joint(services, space, top, self.search, self.config)
            top = top[: self.config.top_k]
            won = top[0][4]  # the confidence over the winning resting pose's grid; the heat map over all
            assessed = self._assess(services[won], space, outs[won], top[0][:3], rests[won].pose, over=outs)
            if known is not None:
                extra["known"] = _counted(known, before)
            wall_s = time.perf_counter() - t_start
            if probe is not None:  # a diagnostic: timed apart, not part of the search's total
                t_probe = time.perf_counter()
                service = over_rests.with_rest(dataclasses.replace(first, known=None), probe_resting or rests[won].pose)
                extra["probe"] = probe_cell(service, space, probe, self.search)
                timings["probe"] = time.perf_counter() - t_probe
        finally:
            if bar is not None:
                bar.close()
        timings["total"] = wall_s
        evaluated, stats, search_extra = over_rests.combined_extra(outs, self.search)
        out = Outcome(np.concatenate([o.scores for o in outs]), evaluated, stats, extra={**search_extra, **extra})
        cands = []
        for x, y, yaw, sc, p in top:
            R, tr = model_to_camera(table, rests[p].pose, x, y, yaw)
            cands.append(Candidate(x, y, yaw, sc, pose_matrix(R[0], tr[0]), rests[p].label))
        result = self._result_of(cands, len(space) * len(rests), out, timings, choice, space, assessed)
        best = over_rests.per_rest_best(outs)
        result.resting = RestingChoice(rests[won], won, rests, best, [o.evaluated for o in outs])
        return result

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
        return self.scoring(image_rgb, camera, table, resting).score((x_m, y_m, yaw_rad))

    def bounds_and_scores(
        self, image_rgb: np.ndarray, camera: Camera, table: Table, resting: RestingPose, space: SearchSpace
    ) -> dict[str, np.ndarray]:
        """Every candidate's silhouette bound and score (analysis of the pruned search; nothing pruned):
        arrays x_m, y_m, yaw_rad (table frame), bound, score; -inf where a candidate shows no feature point."""
        image_rgb, camera = self._scaled(image_rgb, camera)
        service = self._service(image_rgb, camera, table, resting, self.renderer, {}, None)
        x, y, yaw = space.candidates()
        c = service.candidates(x, y, yaw)
        bounds, scores = np.full(len(x), -np.inf), np.full(len(x), -np.inf)
        stats = searches.SearchStats()
        service.bound_some(c, c.live, bounds, stats)
        service.score_some(c, c.live, scores, stats)
        return {"x_m": x, "y_m": y, "yaw_rad": yaw, "bound": bounds, "score": scores}

    def _pick_renderer(self, camera: Camera, table: Table, resting: RestingPose, space: SearchSpace) -> RendererChoice:
        """The renderer for this search (--renderer auto: render.auto_renderer, from the median box of
        up to 256 of the space's candidates, drawn with a fixed seed, on the CPU); nothing is changed."""
        if self.config.renderer != "auto":
            return RendererChoice(self.renderer_for(self.config.renderer), None)
        median = None
        if wp.get_device(self.device).is_cpu:
            R, t = model_to_camera(table, resting, *space.sample(256, seed=0))
            boxes = self.boxes(camera, R, t)
            shown = (boxes[:, 2] > 0) & (boxes[:, 3] > 0)  # -1: behind the camera, 0: outside the image
            areas = boxes[shown, 2].astype(np.int64) * boxes[shown, 3]
            median = float(np.median(areas)) if len(areas) else 0.0
        method = auto_renderer(self.device, int(len(self.mesh.faces)), median or 0.0)
        return RendererChoice(self.renderer_for(method), median)

    def _scaled(self, image_rgb: np.ndarray, camera: Camera) -> tuple[np.ndarray, Camera]:
        """The photo and camera the search runs on (image_scale applied)."""
        if self.config.image_scale != 1.0:
            return _rescale(check_rgb(image_rgb), camera, self.config.image_scale)
        return image_rgb, camera


def _counted(known: KnownScores, before: dict) -> dict:
    """What one search took from and kept in its known scores (search/known.py), the probe left out."""
    now = known.to_dict()
    return {k: now[k] - before[k] for k in now}


def _bar(progress: bool, desc: str):
    """A progress bar over candidate poses (its total grows as searches add theirs), or None."""
    if not progress:
        return None
    return tqdm.tqdm(total=0, unit="pose", desc=desc, leave=False)


def _rescale(image_rgb: np.ndarray, camera: Camera, factor: float) -> tuple[np.ndarray, Camera]:
    """The photo resized (area filter) and its camera with it; poses stay in metres, so results do not change frame."""
    if image_rgb.shape[:2] != (camera.height, camera.width):
        raise PerchError(
            f"image is {image_rgb.shape[1]}x{image_rgb.shape[0]} but the camera is {camera.width}x{camera.height}"
        )
    small = camera.scaled(factor)
    img = Image.fromarray(image_rgb).resize((small.width, small.height), Image.Resampling.BOX)
    return np.asarray(img), small
