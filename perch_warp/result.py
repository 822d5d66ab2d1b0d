"""What a search returns, and its JSON form (metres and radians inside, BOP's mm beside).

`Result.info` is a `SearchInfo`: the method's settings, what ran (search, renderer, conv form) and what
it cost, as typed fields; the search's own facts (pruning counts, pyramid levels, "refine", "probe")
stay in its `extra` dict because each search has its own. `Result.to_dict()` is the --out JSON: the
fixed fields in a fixed order, then `extra`'s keys, at the top level beside "pose" and "top_k".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .confidence import Confidence
    from .score_map import ScoreMap


@dataclass
class Candidate:
    x_m: float
    y_m: float
    yaw_rad: float
    score: float
    T_m2c: np.ndarray  # 4x4, model -> camera, metres
    rest: str | None = None  # the resting pose's label, in a search over several (else None)

    def to_dict(self) -> dict:
        out = {
            "x_m": self.x_m,
            "y_m": self.y_m,
            "yaw_deg": math.degrees(self.yaw_rad),
            "yaw_rad": self.yaw_rad,
            "score": self.score,
            "cam_R_m2c": self.T_m2c[:3, :3].reshape(-1).tolist(),
            "cam_t_m2c_mm": (self.T_m2c[:3, 3] * 1000.0).tolist(),
        }
        if self.rest is not None:
            out["rest"] = self.rest
        return out


@dataclass
class RestingChoice:
    """Which resting pose won a search over several (perch_warp.resting.Rest), and each pose's best.

    `won`: the winning Rest (label: the face down, and roll; pose.z_m: the model origin's height above
    the table top, metres); `index`: its position in `rests`; `best_scores[i]`: rests[i]'s best grid
    score (-inf where it showed nothing); `evaluated[i]`: candidates scored under rests[i]."""

    won: object  # perch_warp.resting.Rest
    index: int
    rests: list
    best_scores: list[float]
    evaluated: list[int]

    @property
    def label(self) -> str:
        return self.won.label

    @property
    def z_m(self) -> float:
        return self.won.pose.z_m

    def to_dict(self) -> dict:
        return {
            **self.won.to_dict(),
            "index": self.index,
            "searched": [
                {"label": r.label, "z_m": r.pose.z_m, "best_grid_score": s if math.isfinite(s) else None}
                | {"evaluated": n}
                for r, s, n in zip(self.rests, self.best_scores, self.evaluated, strict=True)
            ],
        }


@dataclass
class SearchInfo:
    """How a search ran: its settings, the forms of kernels #1 and #2 chosen, and its counters."""

    weights: str  # where the conv1 weights came from (FeatureWeights.source)
    stride_px: int  # feature-grid stride, pixels
    alpha: float  # occlusion limit: top-α share of the feature points averaged
    clusters: int  # k-means clusters of the rarity
    seed: int  # k-means seed
    score: str  # the score's name (perch_warp.score_terms)
    search: str  # the search that ran ("auto" resolved)
    search_option: str  # as asked: "auto" or the search itself
    renderer_option: str  # --renderer as asked: auto, bvh or raster
    mesh_faces: int
    median_box_px: float | None  # --renderer auto on the CPU: the rule's median candidate box; else None
    renderer: str  # the form of kernel #1 that ran: bvh or raster
    cull_back_faces: bool  # raster on a closed mesh only
    conv: str  # the form of kernel #2's convolution that ran: warp or torch
    conv_option: str
    image_scale: float
    search_space: str  # SearchSpace.describe()
    evaluated: int  # candidates scored (rendered and compared)
    batches: int
    rays: int  # pixels ray-cast by kernel #1 (the rendered boxes' areas)
    # Batches scored at once; above 1 the per-batch stage timings are CPU seconds summed over threads.
    threads: int
    extra: dict[str, Any] = field(default_factory=dict)  # the search's own facts, "refine", "probe"

    def to_dict(self) -> dict:
        """The JSON keys of the result's top level, in this order; median_box_px only when the rule ran."""
        out = {
            "weights": self.weights,
            "stride_px": self.stride_px,
            "alpha": self.alpha,
            "clusters": self.clusters,
            "seed": self.seed,
            "score": self.score,
            "search": self.search,
            "search_option": self.search_option,
            "renderer_option": self.renderer_option,
            "mesh_faces": self.mesh_faces,
        }
        if self.median_box_px is not None:
            out["median_box_px"] = self.median_box_px
        out.update(
            renderer=self.renderer,
            cull_back_faces=self.cull_back_faces,
            conv=self.conv,
            conv_option=self.conv_option,
            image_scale=self.image_scale,
            search_space=self.search_space,
            evaluated=self.evaluated,
            batches=self.batches,
            rays=self.rays,
            threads=self.threads,
        )
        return {**out, **self.extra}

    @classmethod
    def from_dict(cls, d: dict) -> SearchInfo:
        """The inverse of to_dict (a result JSON's top level; keys of neither kind are left out)."""
        names = [f for f in cls.__dataclass_fields__ if f != "extra"]
        fixed = {k: d.get(k) for k in names}
        skip = {*names, "pose", "top_k", "n_candidates", "n_scored", "timings_s", "device", "confidence", "resting"}
        return cls(**fixed, extra={k: v for k, v in d.items() if k not in skip})


@dataclass
class Result:
    """The best pose on the table, the runners-up, and what it took."""

    best: Candidate
    top_k: list[Candidate]
    n_candidates: int
    n_scored: int
    timings_s: dict[str, float]
    device: str
    info: SearchInfo
    # The resting pose that won, in a search over several (Engine.estimate given a list); else None.
    resting: RestingChoice | None = None
    # How sure the answer is (perch_warp.confidence) and the best score over yaw per table cell
    # (perch_warp.score_map); None where a Result is built without them.
    confidence: Confidence | None = None
    heatmap: ScoreMap | None = None

    @property
    def x_m(self) -> float:
        return self.best.x_m

    @property
    def y_m(self) -> float:
        return self.best.y_m

    @property
    def yaw_rad(self) -> float:
        return self.best.yaw_rad

    @property
    def score(self) -> float:
        return self.best.score

    @property
    def T_m2c(self) -> np.ndarray:
        return self.best.T_m2c

    @property
    def timings(self) -> dict[str, float]:
        return self.timings_s

    def to_dict(self) -> dict:
        return {
            "pose": self.best.to_dict(),
            "top_k": [c.to_dict() for c in self.top_k],
            "n_candidates": self.n_candidates,
            "n_scored": self.n_scored,
            "timings_s": self.timings_s,
            "device": self.device,
            **self.info.to_dict(),
            # Added after the search's keys, so that those keep their order (a user-facing format).
            "confidence": None if self.confidence is None else self.confidence.to_dict(),
            **({"resting": self.resting.to_dict()} if self.resting is not None else {}),
        }
