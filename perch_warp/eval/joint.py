"""`eval --joint`: every image's targets searched together, then the joint step (perch_warp.objects).

Each target's journalled answer is the joint one; its own search's best rides along in details["joint"],
so the summary can say, paired per target, what the joint step changed. An image whose targets are
partly journalled (a run killed between two of its targets) is searched again whole, so the joint step
always sees every target of the image; only the missing targets are returned.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..bop import TableCache
from ..errors import PerchError
from ..objects import estimate_objects
from .journal import Done
from .protocol import (
    EngineEstimator,
    Outcome,
    SpaceFn,
    TargetRunner,
    _add_space_details,
    _image,
    failure_reason,
    prepare_job,
    stops_the_run,
)


def joint_runner(make_estimator, occluders: str = "answers") -> TargetRunner:
    """Images one after another in this process, each image's targets searched together (`occluders`:
    perch_warp.objects' second pass with "answers")."""

    def run(todo, tables: TableCache, space_fn: SpaceFn, model_paths: dict[int, Path]) -> Iterator[Outcome]:
        state = {"estimator": None, "image_key": None, "image": None}
        wanted = {t.key for _, t in todo}
        images = list({(im.scene_id, im.im_id): im for im, _ in todo}.values())  # image order, once each
        for im in images:
            mine = [t for t in im.targets if t.key in wanted]
            try:
                if state["estimator"] is None:
                    state["estimator"] = make_estimator(model_paths)
                yield from _image_outcomes(im, mine, state, tables, space_fn, occluders)
            except Exception as e:  # noqa: BLE001 - every target of the image fails with the reason
                if stops_the_run(e):
                    raise
                for t in mine:
                    yield t, failure_reason(e)

    return run


def _image_outcomes(
    im, mine: list, state: dict, tables: TableCache, space_fn: SpaceFn, occluders: str
) -> Iterator[Outcome]:
    """The image's targets in `mine` (the others only join the joint step), or their failures."""
    jobs, failures = [], {}
    for t in im.targets:
        try:
            jobs.append(prepare_job(im, t, tables, space_fn))
        except PerchError as e:
            failures[t.key] = failure_reason(e)
    for t in mine:
        if t.key in failures:
            yield t, failures[t.key]
    if not jobs:
        return
    image = _image(state, im)
    done = estimate_image(state["estimator"], jobs, image, occluders)
    for t in mine:
        if t.key in done:
            yield t, done[t.key]


def estimate_image(estimator: EngineEstimator, jobs: list, image_rgb: np.ndarray, occluders: str = "answers") -> dict:
    """Done per target key: the joint answers of one image's targets (jobs: prepare_job's, one image);
    with occluders "answers" the second pass's, the first pass's joint answer in details["occluders"]."""
    first = jobs[0]
    if any(j.space.describe() != first.space.describe() for j in jobs):
        raise PerchError("eval --joint needs one search region per image (a region function that ignores the object)")
    engines = [estimator.engine(j.target.obj_id) for j in jobs]  # each built on first use
    searched = [estimator.searched(j.target, j.resting) for j in jobs]
    probes = [estimator.probe(j.target, j.table, j.resting) for j in jobs]
    names = [f"obj {j.target.obj_id}" for j in jobs]
    t0 = time.perf_counter()
    answers, choice = estimate_objects(
        engines, names, image_rgb, first.camera, first.table, searched, first.space, probes=probes,
        occluders=occluders,
    )  # fmt: skip
    # Per target: the image's search time shared equally (one photo, the searches of both passes, the joint
    # steps), the ground truth's cells (diagnostics, probed in each pass) left out.
    passes = [a.result for a in answers] + [a.first_pass.result for a in answers if a.first_pass is not None]
    dt = (time.perf_counter() - t0 - sum(r.timings["probe"] for r in passes)) / len(jobs)
    out = {}
    for n, (j, e, a) in enumerate(zip(jobs, engines, answers, strict=True)):
        est = estimator.estimate_of(e, a.result, j.camera, a.best)
        own = a.result.best
        est.details["joint"] = {
            "changed": a.changed,
            "peak": a.pick,
            "peaks": len(a.peaks),
            "own_R_m2c": own.T_m2c[:3, :3].tolist(),
            "own_t_m2c_m": own.T_m2c[:3, 3].tolist(),
            "own_score": own.score,
            "method": choice.method,
            "conflicts_left": len(choice.conflicts),
            # what its own best conflicted with, when the step moved it (which answer, and why)
            "moved_by": [{"obj_id": jobs[k].target.obj_id, "why": why} for k, why in choice.moved_by(n)],
        }
        if a.first_pass is not None:
            f = a.first_pass.best
            est.details["occluders"] = {
                **a.result.info.extra.get("hidden", {}),
                "first_R_m2c": f.T_m2c[:3, :3].tolist(),
                "first_t_m2c_m": f.T_m2c[:3, 3].tolist(),
                "first_score": f.score,
                "changed": a.second_pass_changed,
                # the cost of each pass's own search (probe left out) and the first pass's scores reused
                "first_total_s": a.first_pass.result.timings["total"],
                **a.result.info.extra.get("known", {}),
            }
        est.details["table"] = j.table_how
        _add_space_details(est.details, j.space, j.table, j.target)
        out[j.target.key] = Done(
            j.target.obj_id, est.R_m2c, est.t_m2c_m, est.score, dt, est.details, heatmap=est.heatmap
        )
    return out
