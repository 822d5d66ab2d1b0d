"""The engine's method parameters (EngineConfig) and the searches it knows by name."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import PerchError
from .peaks import peak_pool
from .render import RENDERERS
from .score import CONVS
from .score_terms import DEFAULT_SCORE, parse_score

SEARCHES = ("auto", "exhaustive", "pruned", "coarse-to-fine")


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
    # silhouette bound can reach it (perch_warp.search.pruned); "coarse-to-fine": a pyramid (search.pyramid);
    # "auto": pruned on the CPU (measured faster there, docs/performance.md), exhaustive on a GPU
    # (the pruned search's GPU speed is not measured yet). Both give the same top-k.
    search: str = "auto"
    coarse_xy_m: float = 0.02  # coarse-to-fine: the first lattice's x/y step
    coarse_yaw_rad: float = math.radians(10.0)  # coarse-to-fine: the first lattice's yaw step
    # coarse-to-fine: how many best candidates each finer level refines. 512: the first lattice's cost
    # dominates, so a wide beam costs little more and agrees with the exact search more often
    # (docs/performance.md, "Coarse-to-fine against exhaustive")
    beam: int = 512
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
    # Refine this many distinct yaws of each peak's place (perch_warp.peaks.yaw_peaks: every grid yaw
    # there scored, its best local maxima more than two yaw steps apart): on the grid a place's best yaw
    # can lie outside the refinement's window around the true yaw. 1: the place's best grid yaw only.
    refine_yaws: int = 1
    # How kernel #1 finds each ray's surface (perch_warp.render): "bvh", "raster" (the same images),
    # or "auto": per search on the CPU, raster unless the mesh has many faces per pixel of the
    # candidates' boxes (render.auto_renderer); bvh on a GPU (the raster form is not measured there).
    renderer: str = "auto"
    # How kernel #2 convolves the candidates' windows (perch_warp.score): "warp", "torch" (conv2d on
    # each candidate's composited crop; the same values up to float rounding), or "auto": torch on the
    # CPU (measured faster there), warp on a GPU (torch is not measured there) unless the score has the
    # centre term, as the default has, which only the torch form computes (score.auto_conv).
    conv: str = "auto"
    # What a candidate's score is made of (perch_warp.score_terms): a name ("thesis": the thesis's
    # formula; "grid-tolerant": the same with a grid stage that tolerates a one-cell misalignment;
    # "centred": grid-tolerant with the centred cosine blended in; "centred-4starts": centred with the
    # rarity from the best of four k-means starts; "centred-direction": centred-4starts with the rarity
    # clustered on the direction of conv1's response, chosen on the development set, docs/accuracy.md) or
    # terms over the thesis's, e.g. "shift=1,shrink=16".
    score: str = DEFAULT_SCORE

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
        if self.refine_yaws < 1:
            raise PerchError(f"refine_yaws (--refine-yaws) must be at least 1, got {self.refine_yaws}")
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

    @property
    def pool(self) -> int:
        """Best grid candidates a search keeps: the top-k reported, or more to find distinct peaks among."""
        return peak_pool(self.top_k, self.refine_peaks if self.refine else 1)
