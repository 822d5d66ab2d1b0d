"""Several objects in one photo: the photo's features and rarity once, each object's own search, then the
joint step (perch_warp.joint) that makes the answers consistent.

Each object is searched with at least `peaks` distinct peaks refined (EngineConfig.refine_peaks, see
perch_warp.peaks), so its own answer is the best of those (what `--refine-peaks K` gives one object) and
the joint step chooses among them. An object's answer changes only when its own best conflicts with
another object's answer in every better combination.

With `occluders="answers"` a second pass follows: each object is searched again with the other objects'
first-pass answers as occluders (perch_warp.hidden: its points they cover, nearer the camera, are left
out of its score and bound), then the joint step chooses again. That pass needs no rule against one
region explained twice (the hidden-share conflict of perch_warp.joint): what a nearer answer covers no
longer counts for the farther object. The occluders are the first pass's answers; one second pass, not
iterated. The first pass keeps each object's scores (perch_warp.search.known) and the second scores
anew only the candidates an answer can hide: the same answers as scoring every candidate again, bit
for bit, at the touched candidates' cost.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import joint
from .camera import Camera
from .engine import Engine
from .errors import PerchError
from .hidden import DEFAULT_BETA
from .result import Candidate, Result
from .search.known import KnownScores
from .search_space import SearchSpace
from .table import Table

# Where the objects' occluders come from: none, or the other objects' first-pass answers (module doc).
OCCLUDERS = ("none", "answers")


@dataclass
class ObjectAnswer:
    """One object's search and the joint step's answer for it."""

    name: str
    result: Result  # the object's own search (result.best: its own answer)
    peaks: list[Candidate]  # its distinct refined peaks, best first (peaks[0] is result.best)
    pick: int  # the peak the joint step chose
    first_pass: ObjectAnswer | None = None  # with occluders="answers": the first pass's answer

    @property
    def best(self) -> Candidate:
        """The joint answer."""
        return self.peaks[self.pick]

    @property
    def changed(self) -> bool:
        """Whether the joint step moved this object away from its own best."""
        return self.pick != 0

    @property
    def second_pass_changed(self) -> bool:
        """With a first pass (occluders "answers"): whether this answer differs from the first pass's."""
        f, b = self.first_pass.best, self.best
        return (f.x_m, f.y_m, f.yaw_rad, f.rest) != (b.x_m, b.y_m, b.yaw_rad, b.rest)


def refined_peaks(result: Result) -> list[Candidate]:
    """The object's distinct refined peaks, best first: the first entries of its top-k (search.refine)."""
    refine = result.info.extra.get("refine", {})
    n = len(refine.get("peaks", [])) or 1
    return result.top_k[:n]


def estimate_objects(
    engines: Sequence[Engine],
    names: Sequence[str],
    image_rgb: np.ndarray,
    camera: Camera,
    table: Table,
    restings: Sequence,
    space: SearchSpace,
    progress: bool = False,
    overlap_m: float = joint.DEFAULT_OVERLAP_M,
    probes: Sequence[dict] | None = None,
    occluders: str = "answers",
    beta: float = DEFAULT_BETA,
) -> tuple[list[ObjectAnswer], joint.JointChoice]:
    """Every object's answer in one photo (module doc). engines[i] searches object names[i] under
    restings[i] (a RestingPose or a list of perch_warp.resting.Rest, as Engine.estimate takes); all engines
    share weights, device and method settings (built with joint_config), so the photo is computed once.
    probes[i] (for evaluation): Engine.estimate's probe and probe_resting for object i. `occluders`:
    "none", or "answers" for the second pass (module doc) with the reduction's `beta` (perch_warp.hidden)."""
    if occluders not in OCCLUDERS:
        raise PerchError(f"occluders must be one of {', '.join(OCCLUDERS)}, got {occluders!r}")
    if not engines:
        raise PerchError("no object to search")
    first = engines[0]
    for e in engines[1:]:
        if e.device != first.device or e.config != first.config or e.weights.source != first.weights.source:
            raise PerchError("the objects' engines must share device, weights and method settings")
    photo = first.photo(image_rgb, camera)
    probes = probes if probes is not None else [{}] * len(engines)

    second = occluders == "answers" and len(engines) > 1
    known = [KnownScores(photo) if second else None for _ in engines]

    def search(hidden: list | None) -> list[ObjectAnswer]:
        out = []
        for n, (engine, name, resting) in enumerate(zip(engines, names, restings, strict=True)):
            result = engine.estimate(
                image_rgb, camera, table, resting, space, progress=progress, photo=photo,
                hidden=None if hidden is None else hidden[n], known=known[n], **probes[n],
            )  # fmt: skip
            out.append(ObjectAnswer(name, result, refined_peaks(result), 0))
        return out

    answers = search(None)
    choice = _pick(answers, choose_jointly(engines, answers, camera, table, overlap_m))
    if second:
        hidden = [
            e.hidden_by(camera, [(engines[j], a.best.T_m2c) for j, a in enumerate(answers) if j != n], beta)
            for n, e in enumerate(engines)
        ]
        firsts, answers = answers, search(hidden)
        for a, f in zip(answers, firsts, strict=True):
            a.first_pass = f
        choice = _pick(answers, choose_jointly(engines, answers, camera, table, overlap_m, hidden_rule=False))
    return answers, choice


def _pick(answers: list[ObjectAnswer], choice: joint.JointChoice) -> joint.JointChoice:
    """Each answer's pick set from the joint step's choice; the choice."""
    for a, pick in zip(answers, choice.picks, strict=True):
        a.pick = pick
    return choice


def choose_jointly(
    engines: Sequence[Engine],
    answers: list[ObjectAnswer],
    camera: Camera,
    table: Table,
    overlap_m: float,
    hidden_rule: bool = True,
) -> joint.JointChoice:
    """perch_warp.joint.choose over the objects' peaks: footprints from each mesh's hull, silhouettes
    rendered at full resolution, conflicts under the engines' α (without the hidden-share rule when
    `hidden_rule` is False: the second pass, whose scores leave the hidden points out)."""
    peaks = [[_peak(e, c, camera, table) for c in a.peaks] for e, a in zip(engines, answers, strict=True)]
    alpha = engines[0].config.alpha

    def clash(i: int, a: int, j: int, b: int) -> str | None:
        return joint.conflict(peaks[i][a], peaks[j][b], alpha, overlap_m, hidden_rule)

    return joint.choose([[c.score for c in a.peaks] for a in answers], clash)


def _peak(engine: Engine, cand: Candidate, camera: Camera, table: Table) -> joint.Peak:
    T = cand.T_m2c
    _, mask = engine.render(camera, T)
    centre_m = engine.hull_m.mean(axis=0) @ T[:3, :3].T + T[:3, 3]
    heights = joint.height_range(table, T, engine.hull_m)
    return joint.Peak(
        cand.score, joint.footprint(table, T, engine.hull_m), mask, float(np.linalg.norm(centre_m)), heights
    )
