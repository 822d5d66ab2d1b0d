"""The search engine: build once per mesh (and weights, device), call once per photo.

Stages: photo features -> rarity (k-means) -> candidate poses and boxes ->
per batch: render (kernel #1) -> features x similarity x rarity (kernel #2) ->
top-α mean -> best pose.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from .camera import Camera
from .errors import PerchError
from .features import FeatureWeights
from .image import check_rgb
from .mesh import ObjectMesh
from .rarity import rarity as rarity_fn
from .render import MeshRenderer, project_boxes
from .result import Candidate, Result
from .score import FeatureScorer, grid_boxes, grid_shape, top_alpha_mean
from .search_space import SearchSpace
from .table import RestingPose, Table, model_to_camera, pose_matrix


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

    def __post_init__(self) -> None:
        if not (0.0 < self.alpha <= 1.0) or not math.isfinite(self.alpha):
            raise PerchError(f"alpha (occlusion limit) must be in (0, 1], got {self.alpha}")
        if self.stride < 1:
            raise PerchError(f"stride must be a positive number of pixels, got {self.stride}")
        if self.clusters < 1:
            raise PerchError(f"clusters must be at least 1, got {self.clusters}")
        if self.top_k < 1:
            raise PerchError(f"top_k must be at least 1, got {self.top_k}")


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
        self.renderer = MeshRenderer(mesh, self.device)
        self.scorer = FeatureScorer(weights, self.device, self.config.stride, self.config.relu)
        self.scorer.warm_up()
        wp.load_module("perch_warp.kernels.render", device=self.device)
        self.setup_s = time.perf_counter() - t0
        self.hull_m = mesh.hull_points_m()

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
    ) -> Result:
        """Best (x, y, yaw) of the object in the photo; see the module doc for the stages."""
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
        timings: dict[str, float] = {}

        def lap(stage: str, t0: float) -> float:
            wp.synchronize_device(self.device)
            t1 = time.perf_counter()
            timings[stage] = timings.get(stage, 0.0) + (t1 - t0)
            return t1

        t = time.perf_counter()
        image = self.scorer.image_to_device(image_rgb)
        obs = self.scorer.observed_features(image)
        t = lap("photo_features", t)
        feats = obs.numpy().reshape(rows * cols, -1)
        rar = rarity_fn(feats, cfg.clusters, cfg.seed).reshape(rows, cols)
        norms = np.linalg.norm(feats.astype(np.float64), axis=1).reshape(rows, cols).astype(np.float32)
        with wp.ScopedDevice(self.device):
            rar_wp = wp.array(rar, dtype=float)
            norm_wp = wp.array(norms, dtype=float)
        t = lap("rarity", t)

        x, y, yaw = space.candidates()
        R, tr = model_to_camera(table, resting, x, y, yaw)
        boxes = project_boxes(camera, self.hull_m, R, tr)
        if np.any(boxes[:, 2] < 0):
            n_bad = int((boxes[:, 2] < 0).sum())
            raise PerchError(
                f"{n_bad} of {len(boxes)} candidate poses are behind or within {0.02} m of the camera: "
                "check the table frame and the search ranges"
            )
        gboxes = grid_boxes(boxes, rows, cols, ks, cfg.stride)
        live = np.flatnonzero(gboxes[:, 2] * gboxes[:, 3] > 0)
        if len(live) == 0:
            raise PerchError(f"the search grid projects outside the image ({space.describe()})")
        t = lap("candidates", t)

        scores = np.full(len(x), -np.inf)
        n_pts = np.zeros(len(x), dtype=np.int64)
        budget = cfg.batch_pixels or _batch_pixels(self.device)
        sizes = boxes[live, 2].astype(np.int64) * boxes[live, 3]
        batches = _split_by_budget(sizes, budget)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(live), unit="pose", desc=f"search on {self.device}", leave=False)
        for lo, hi in batches:
            idx = live[lo:hi]
            batch = self.renderer.render(camera, R[idx], tr[idx], boxes[idx])
            t = lap("render", t)
            vals, pt_off = self.scorer.score_points(image, batch, gboxes[idx], obs, norm_wp, rar_wp)
            t = lap("features_score", t)
            vals_np = vals.numpy()
            t = lap("transfer", t)
            s, n = top_alpha_mean(vals_np, pt_off, cfg.alpha)
            scores[idx] = s
            n_pts[idx] = n
            t = lap("reduction", t)
            if bar is not None:
                bar.update(len(idx))
        if bar is not None:
            bar.close()

        # Stable order: ties go to the earlier candidate, so results are reproducible.
        order = np.argsort(-scores, kind="stable")[: cfg.top_k]
        cands = [
            Candidate(float(x[i]), float(y[i]), float(yaw[i]), float(scores[i]), pose_matrix(R[i], tr[i]))
            for i in order
        ]
        timings["total"] = sum(timings.values())
        return Result(
            best=cands[0],
            top_k=cands,
            n_candidates=len(x),
            n_scored=int(np.isfinite(scores).sum()),
            timings_s=timings,
            device=self.device,
            info={
                "weights": self.weights.source,
                "stride_px": cfg.stride,
                "alpha": cfg.alpha,
                "clusters": cfg.clusters,
                "seed": cfg.seed,
                "search_space": space.describe(),
                "batches": len(batches),
                "mean_points_per_candidate": float(n_pts[live].mean()),
            },
        )


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
