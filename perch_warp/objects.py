"""Several objects in one photo: the photo's features and rarity once, each object's own search, then the
joint step (perch_warp.joint) that makes the answers consistent.

Each object is searched with at least `peaks` distinct peaks refined (EngineConfig.refine_peaks, see
perch_warp.peaks), so its own answer is the best of those (what `--refine-peaks K` gives one object) and
the joint step chooses among them. An object's answer changes only when its own best conflicts with
another object's answer in every better combination.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import joint
from .camera import Camera
from .engine import Engine
from .errors import PerchError
from .result import Candidate, Result
from .search_space import SearchSpace
from .table import Table


@dataclass
class ObjectAnswer:
    """One object's search and the joint step's answer for it."""

    name: str
    result: Result  # the object's own search (result.best: its own answer)
    peaks: list[Candidate]  # its distinct refined peaks, best first (peaks[0] is result.best)
    pick: int  # the peak the joint step chose

    @property
    def best(self) -> Candidate:
        """The joint answer."""
        return self.peaks[self.pick]

    @property
    def changed(self) -> bool:
        """Whether the joint step moved this object away from its own best."""
        return self.pick != 0


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
) -> tuple[list[ObjectAnswer], joint.JointChoice]:
    """Every object's answer in one photo (module doc). engines[i] searches object names[i] under
    restings[i] (a RestingPose or a list of perch_warp.resting.Rest, as Engine.estimate takes); all engines
    share weights, device and method settings (built with joint_config), so the photo is computed once.
    probes[i] (for evaluation): Engine.estimate's probe and probe_resting for object i."""
    if not engines:
        raise PerchError("no object to search")
    first = engines[0]
    for e in engines[1:]:
        if e.device != first.device or e.config != first.config or e.weights.source != first.weights.source:
            raise PerchError("the objects' engines must share device, weights and method settings")
    photo = first.photo(image_rgb, camera)
    answers = []
    for n, (engine, name, resting) in enumerate(zip(engines, names, restings, strict=True)):
        probe = probes[n] if probes is not None else {}
        result = engine.estimate(image_rgb, camera, table, resting, space, progress=progress, photo=photo, **probe)
        answers.append(ObjectAnswer(name, result, refined_peaks(result), 0))
    choice = choose_jointly(engines, answers, camera, table, overlap_m)
    for a, pick in zip(answers, choice.picks, strict=True):
        a.pick = pick
    return answers, choice


def choose_jointly(
    engines: Sequence[Engine], answers: list[ObjectAnswer], camera: Camera, table: Table, overlap_m: float
) -> joint.JointChoice:
    """perch_warp.joint.choose over the objects' peaks: footprints from each mesh's hull, silhouettes
    rendered at full resolution, conflicts under the engines' α."""
    peaks = [[_peak(e, c, camera, table) for c in a.peaks] for e, a in zip(engines, answers, strict=True)]
    alpha = engines[0].config.alpha

    def clash(i: int, a: int, j: int, b: int) -> str | None:
        return joint.conflict(peaks[i][a], peaks[j][b], alpha, overlap_m)

    return joint.choose([[c.score for c in a.peaks] for a in answers], clash)


def _peak(engine: Engine, cand: Candidate, camera: Camera, table: Table) -> joint.Peak:
    T = cand.T_m2c
    _, mask = engine.render(camera, T)
    centre_m = engine.hull_m.mean(axis=0) @ T[:3, :3].T + T[:3, 3]
    heights = joint.height_range(table, T, engine.hull_m)
    return joint.Peak(
        cand.score, joint.footprint(table, T, engine.hull_m), mask, float(np.linalg.norm(centre_m)), heights
    )
