"""`eval --ray`: the targets of an evaluation searched by Ray workers, their outcomes back to the driver.

The driver (the process that runs `evaluate`) prepares every target (table frame, resting pose, search
region), reads each photo and mesh once and puts them in Ray's object store, and writes every output
itself (perch_warp.eval.protocol._run_targets): the journal, results.csv and the summary are those of a
serial run, so a run can be interrupted and resumed, serial or distributed, either way.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

from ..bop import ImageInfo, TableCache, Target
from ..errors import PerchError
from ..eval.protocol import Outcome, RestSpec, SpaceFn, TargetRunner, failure_reason, prepare_job, stops_the_run
from ..image import load_rgb
from ..mesh import load_mesh
from ..options import SearchTooLarge
from .cluster import WorkerPlan, connect, plan_workers, require_ray
from .pool import DEFAULT_MAX_ATTEMPTS, WorkerPool, _log


@dataclass
class RayOptions:
    """Where and how wide: `address` None starts a local cluster (`local_cpus` CPU slots, default all
    cores), else joins it ("auto": the cluster `ray start` made on this machine; "HOST:PORT")."""

    address: str | None = None
    n_workers: int | None = None
    cpus_per_worker: int = 1
    max_attempts: int = DEFAULT_MAX_ATTEMPTS
    local_cpus: int | None = None


@dataclass
class _Shared:
    """Photos and meshes in the object store: each put once, a photo dropped when its last target is done."""

    ray: object
    left: Counter  # image key -> targets not yet answered
    images: dict = field(default_factory=dict)  # image key -> [ref], or the reading's failure (str)
    meshes: dict = field(default_factory=dict)  # obj_id -> [ref], or the loading's failure (str)

    def image(self, im: ImageInfo) -> list:
        key = (im.scene_id, im.im_id)
        if key not in self.images:
            try:
                self.images[key] = [self.ray.put(load_rgb(im.rgb))]
            except Exception as e:  # noqa: BLE001 - every target of the photo fails with its reason
                self.images[key] = failure_reason(e)
        return _or_raise(self.images[key])

    def mesh(self, obj_id: int, path: Path) -> list:
        if obj_id not in self.meshes:
            try:
                self.meshes[obj_id] = [self.ray.put(load_mesh(path))]
            except Exception as e:  # noqa: BLE001 - every target of the object fails with its reason
                self.meshes[obj_id] = failure_reason(e)
        return _or_raise(self.meshes[obj_id])

    def answered(self, im: ImageInfo) -> None:
        key = (im.scene_id, im.im_id)
        self.left[key] -= 1
        if self.left[key] == 0:
            self.images.pop(key, None)


def _or_raise(entry):
    if isinstance(entry, str):
        raise PerchError(entry)
    return entry


def ray_runner(
    options: RayOptions,
    weights_spec: str,
    device: str | None,
    config,
    on_outcome: Callable[[WorkerPool, Target], None] | None = None,
    rest: RestSpec = RestSpec(),
) -> TargetRunner:
    """A TargetRunner on Ray workers: `config` (EngineConfig), `rest` (the resting poses searched) and the
    weights of `weights_spec` (read here, once) for every target; `device` None: GPUs when the cluster has
    them. `on_outcome(pool, target)` is called after each outcome (monitoring; the tests kill a busy worker
    from it)."""

    def run(todo, tables: TableCache, space_fn: SpaceFn, model_paths: dict[int, Path]) -> Iterator[Outcome]:
        ray = require_ray()
        jobs = []
        for im, target in todo:  # prepared here, in target order: a target that cannot be searched fails now
            try:
                jobs.append((im, prepare_job(im, target, tables, space_fn)))
            except Exception as e:  # noqa: BLE001 - recorded with its reason, as in a serial run
                if stops_the_run(e):
                    raise
                yield target, failure_reason(e)
        if not jobs:
            return
        from ..features import load_feature_weights

        weights = load_feature_weights(weights_spec)  # read here: workers need no ../shared
        connected = connect(options.address, options.local_cpus)
        try:
            yield from _run_jobs(ray, jobs, options, weights, device, config, rest, model_paths, on_outcome)
        finally:
            if connected:
                ray.shutdown()

    return run


def _run_jobs(
    ray, jobs, options: RayOptions, weights, device, config, rest: RestSpec, model_paths, on_outcome
) -> Iterator[Outcome]:
    """The prepared jobs through a worker pool; each outcome as it comes back."""
    plan = plan_workers(ray.cluster_resources(), device, options.n_workers, options.cpus_per_worker)
    plan = _fewer_for_few(plan, len(jobs))
    _log(f"ray: {plan.describe()} for {len(jobs)} targets")
    pool = WorkerPool(plan, weights, options.max_attempts)
    shared = _Shared(ray, Counter((im.scene_id, im.im_id) for im, _ in jobs))
    by_key = {job.target.key: (im, job) for im, job in jobs}

    def submit(actor, key, payload):
        im, job = payload
        obj_id = job.target.obj_id
        refs = {"image": shared.image(im), "meshes": {obj_id: shared.mesh(obj_id, model_paths[obj_id])}}
        return actor.run_target.remote(job, config, refs, rest)

    try:
        for key, reply, attempts in pool.run(((j.target.key, (im, j)) for im, j in jobs), submit):
            im, job = by_key[key]
            shared.answered(im)
            if reply.stops:
                raise SearchTooLarge(reply.failure)
            if reply.failure is not None:
                yield job.target, reply.failure
            else:
                reply.value.details["worker"] = {"name": reply.worker, "attempts": attempts}
                yield job.target, reply.value
            if on_outcome is not None:
                on_outcome(pool, job.target)
    finally:
        pool.close()


def _fewer_for_few(plan: WorkerPlan, n_jobs: int) -> WorkerPlan:
    """No more workers than targets: the others would start and build nothing for nothing."""
    return replace(plan, n_workers=min(plan.n_workers, n_jobs))
