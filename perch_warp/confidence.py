"""How sure an answer is: the margin between the best pose and the best clearly different pose.

Definition (grid level, score units):

    margin = S_near - S_far

S_near is the best grid score among the searched grid's poses *not* clearly different from the
answer (the returned, refined pose), S_far the best grid score among those clearly different from it.
A pose is clearly different from the answer when its (x, y) lies more than DIFFERENT_XY_M (2 cm)
from the answer's, or its yaw differs by more than DIFFERENT_YAW_RAD (15°), wrapped, *and* that yaw
offset moves the object's shape more than a 15° turn does: the model's points turned by it about
the table normal (through the model origin) lie farther from themselves, by ADD-S (the evaluation's
metric), than when turned by ±15°, and than SYMMETRY_TOL_M (2 mm). So symmetries do not count, nor
offsets near them: a can turned about its axis (no yaw counts: only x, y tell poses apart), a box
turned by 180° ± less than 15°; ADD-S, by which answers are judged right, does not count them either.
The texture is ignored here (a can's label facing away is the same pose to ADD-S).

Both maxima are over grid scores (the refined answer's score is not used: the runners-up are not
refined, and grid against grid is the same resolution). A large margin: no other place or
orientation explains the photo nearly as well; near 0 (or negative, when --refine-peaks chose a
peak that was not the grid's best): another clearly different pose is as good.

Exactness: with the exhaustive search every grid score is known. The pruned search leaves
candidates unscored whose bound is below its top-k; where one of those could beat the best known
score of S_near's or S_far's set, `settle` scores them, best bound first, until none can: the margin
is then exact (their count is `rescored`). The coarse-to-fine search knows only the grid points it
visited: its margin is over those (exact = False).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .pose_error import subsample_points
from .score_map import Knowledge
from .search_space import SearchSpace
from .table import rot_z

DIFFERENT_XY_M = 0.02
DIFFERENT_YAW_RAD = math.radians(15.0)
SYMMETRY_TOL_M = 0.002
# Points of the model (metres) used to test yaw symmetries: plenty for a 2 mm test.
SYMMETRY_POINTS = 1000


@dataclass
class Confidence:
    """margin = near_score - runner_up's score (None when no clearly different pose shows a feature
    point); runner_up: (x_m, y_m, yaw_rad, score), table frame, the best clearly different grid pose;
    exact: both maxima exact (False: coarse-to-fine's visited points only); yaw_ignored: every yaw
    offset is a symmetry of the object (only x, y tell poses apart); rescored: candidates the pruned
    search had left out and that were scored for this."""

    margin: float | None
    near_score: float
    runner_up: tuple[float, float, float, float] | None
    exact: bool
    yaw_ignored: bool
    rescored: int = 0

    def to_dict(self) -> dict:
        r = self.runner_up
        runner = None if r is None else {"x_m": r[0], "y_m": r[1], "yaw_deg": math.degrees(r[2]), "score": r[3]}
        return {
            "margin": self.margin,
            "near_score": self.near_score,
            "runner_up": runner,
            "exact": self.exact,
            "yaw_ignored": self.yaw_ignored,
            "rescored": self.rescored,
            "definition": f"best grid score within {DIFFERENT_XY_M * 100:g} cm and {math.degrees(DIFFERENT_YAW_RAD):g} "
            "deg of the answer (yaw symmetries of the shape aside) minus the best grid score farther away",
        }

    def line(self) -> str:
        """One line for the CLI."""
        if self.margin is None:
            return "confidence: no clearly different pose shows a feature point (margin undefined)"
        x, y, yaw, s = self.runner_up
        note = "" if self.exact else " (over the grid points visited only)"
        away = f"> {DIFFERENT_XY_M * 100:g} cm" + ("" if self.yaw_ignored else
                                                   f" or > {math.degrees(DIFFERENT_YAW_RAD):g}° yaw")  # fmt: skip
        return (
            f"confidence: margin {self.margin:.4f}{note} (best grid score {self.near_score:.4f} at the answer; "
            f"{s:.4f} at x = {x:+.4f} m, y = {y:+.4f} m, yaw = {math.degrees(yaw):.0f} deg, the best pose {away} away)"
        )


def yaw_differs(points_m: np.ndarray, R_rest: np.ndarray, offsets_rad: np.ndarray) -> np.ndarray:
    """For each yaw offset (rad): whether it clearly changes the pose of the model (points_m, model frame,
    metres) resting as R_rest (model -> table rotation): more than DIFFERENT_YAW_RAD (wrapped), and the
    model turned by it about the table normal lies farther (ADD-S) from itself than when turned by
    ±DIFFERENT_YAW_RAD, and than SYMMETRY_TOL_M. So symmetries do not count, continuous (a can about its
    axis: every turn within the tolerance) or discrete (a box by 180°), nor offsets near them."""
    offsets = np.asarray(offsets_rad, dtype=np.float64)
    wrapped = np.abs((offsets + math.pi) % (2 * math.pi) - math.pi)
    out = wrapped > DIFFERENT_YAW_RAD + 1e-9
    p = np.asarray(points_m, dtype=np.float64) @ np.asarray(R_rest).T
    tree = cKDTree(p)  # every point, so that sparse sampling does not pass for asymmetry
    q = subsample_points(p, SYMMETRY_POINTS)

    def adds(turn: float) -> float:
        return float(tree.query(q @ rot_z(turn).T, k=1)[0].mean())

    ref = max(SYMMETRY_TOL_M, adds(DIFFERENT_YAW_RAD), adds(-DIFFERENT_YAW_RAD))
    for i in np.flatnonzero(out):
        out[i] = adds(offsets[i]) > ref
    return out


def far_mask(space: SearchSpace, answer: tuple[float, float, float], yaw_differs_fn) -> tuple[np.ndarray, bool]:
    """Flat bool over the space's candidates: clearly different from answer (x_m, y_m, yaw_rad); and
    whether yaw never counts. yaw_differs_fn(offsets_rad) -> bool per offset (see yaw_differs)."""
    xs, ys, yaws = space.axes()
    ax, ay, ayaw = answer
    xy_far = np.hypot(xs[:, None] - ax, ys[None, :] - ay) > DIFFERENT_XY_M + 1e-9
    yaw_far = np.asarray(yaw_differs_fn(yaws - ayaw), dtype=bool)
    far = xy_far[:, :, None] | yaw_far[None, None, :]
    # Ignored: no yaw a clearly different angle away is told apart (a body of revolution).
    wrapped = np.abs((yaws - ayaw + math.pi) % (2 * math.pi) - math.pi)
    ignored = not yaw_far.any() and bool((wrapped > DIFFERENT_YAW_RAD + 1e-9).any())
    return far.reshape(-1), ignored


def settle(k: Knowledge, mask: np.ndarray, score_fn, first: int = 16) -> int:
    """Score (score_fn(flat indices) -> scores) the unknown candidates of `mask` whose upper bound
    exceeds the set's best known score, best bound first, in rounds of growing size, until the set's
    maximum is exact; k is updated in place. Returns how many were scored."""
    n_scored, size = 0, first
    while True:
        best, _, top_unknown = k.set_max(mask)
        # Done when no unknown can beat the best; unbounded unknowns (coarse-to-fine) cannot be settled.
        if top_unknown <= best or top_unknown == np.inf:
            return n_scored
        cand = np.flatnonzero(mask & np.isnan(k.value) & (k.upper > best))
        cand = cand[np.argsort(-k.upper[cand], kind="stable")][:size]
        sc = np.asarray(score_fn(cand), dtype=np.float64)
        k.value[cand], k.upper[cand] = sc, sc
        n_scored += len(cand)
        size *= 2


def grid_confidence(k: Knowledge, space: SearchSpace, answer, yaw_differs_fn, score_fn=None) -> Confidence:
    """The answer's Confidence from what the search knows (k, updated in place when score_fn is given:
    see `settle`); answer: (x_m, y_m, yaw_rad), table frame."""
    far, ignored = far_mask(space, answer, yaw_differs_fn)
    rescored = 0
    if score_fn is not None:
        rescored = settle(k, ~far, score_fn) + settle(k, far, score_fn)
    near, _, near_unknown = k.set_max(~far)
    far_best, i, far_unknown = k.set_max(far)
    exact = near >= near_unknown and far_best >= far_unknown
    if i < 0 or not np.isfinite(far_best):
        return Confidence(None, near, None, exact, ignored, rescored)
    (x,), (y,), (yaw,) = space.at(np.array([i]))
    runner = (float(x), float(y), float(yaw), far_best)
    return Confidence(near - far_best, near, runner, exact, ignored, rescored)
