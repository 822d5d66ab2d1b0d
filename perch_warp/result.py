"""What a search returns, and its JSON form (metres and radians inside, BOP's mm beside)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

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
class Result:
    """The best pose on the table, the runners-up, and what it took."""

    best: Candidate
    top_k: list[Candidate]
    n_candidates: int
    n_scored: int
    timings_s: dict[str, float]
    device: str
    info: dict = field(default_factory=dict)
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
            "confidence": None if self.confidence is None else self.confidence.to_dict(),
            **self.info,
            **({"resting": self.resting.to_dict()} if self.resting is not None else {}),
        }
