"""`estimate_many`: single-image searches for a pipeline, spread over Ray workers, streamed as they finish."""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera, camera_from_entry
from ..config import EngineConfig
from ..image import check_rgb, load_rgb
from ..mesh import load_mesh
from ..result import Result
from ..search_space import SearchSpace
from ..table import RestingPose, Table
from .cluster import connect, plan_workers, require_ray
from .pool import DEFAULT_MAX_ATTEMPTS, WorkerPool


@dataclass(frozen=True)
class EstimateRequest:
    """One search. `image`: RGB uint8 (H, W, 3), or a file read on the driver. `camera`: a BOP
    scene_camera.json entry (`cam_K` in pixels; `cam_R_w2c`/`cam_t_w2c` in mm give the table frame
    unless `table` is given). `mesh`: the object's mesh file (mm or m detected, or `mesh_units`), read
    once on the driver per file and sent to each worker once. `space`: the table-frame grid (metres,
    radians; default the visible table clipped to 1 m, 1 cm / 5 deg); `resting`: default upright;
    `config`: the method (EngineConfig defaults). `id` comes back in the result (default: its index)."""

    image: np.ndarray | str | Path
    camera: dict
    mesh: str | Path
    table: Table | None = None
    space: SearchSpace | None = None
    resting: RestingPose | None = None
    config: EngineConfig = field(default_factory=EngineConfig)
    mesh_units: str = "auto"
    id: Hashable | None = None


@dataclass
class EstimateResult:
    """A request's answer: `result` (perch_warp.result.Result: pose in the table and camera frames,
    metres and radians) or `error` (its one-line reason); `attempts` > 1 when a worker was lost on it."""

    id: Hashable
    index: int  # the request's position in the input
    result: Result | None
    error: str | None
    attempts: int
    worker: str
    seconds: float  # wall time of the call in the worker (engine build included, on a worker's first use)

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass(frozen=True)
class Prepared:
    """A request as a worker gets it: the photo and mesh travel apart, by object-store reference."""

    mesh_key: tuple[str, str]
    camera: Camera
    table: Table
    resting: RestingPose
    space: SearchSpace
    config: EngineConfig


def _prepare(req: EstimateRequest, image: np.ndarray, mesh) -> Prepared:
    """The request's camera, table, resting pose and space, on the driver (bad input fails here)."""
    h, w = image.shape[:2]
    camera = camera_from_entry(req.camera, w, h)
    table = req.table or Table.from_entry(req.camera)
    resting = req.resting or RestingPose.upright(mesh.vertices_m)
    space = req.space or SearchSpace.visible_table(camera, table, 0.01, math.radians(5.0))
    return Prepared((str(Path(req.mesh).resolve()), req.mesh_units), camera, table, resting, space, req.config)


def estimate_many(
    requests: Iterable[EstimateRequest],
    address: str | None = None,
    *,
    n_workers: int | None = None,
    cpus_per_worker: int = 1,
    device: str | None = None,
    weights: str = "auto",
    max_attempts: int = DEFAULT_MAX_ATTEMPTS,
    local_cpus: int | None = None,
) -> Iterator[EstimateResult]:
    """Every request searched on Ray workers (one per GPU, else per `cpus_per_worker` CPUs; `address`
    None starts a local cluster of `local_cpus` slots, or reuses this process's Ray connection),
    yielded as each finishes. A request that fails gives its reason in `error` and is not retried; one
    whose worker is lost is retried on another, up to `max_attempts` times. `weights`: as
    perch_warp.features.load_feature_weights, read here once."""
    ray = require_ray()
    from ..features import load_feature_weights

    reqs = list(requests)
    if not reqs:
        return
    feature_weights = load_feature_weights(weights)
    connected = connect(address, local_cpus)
    try:
        plan = plan_workers(ray.cluster_resources(), device, n_workers, cpus_per_worker)
        pool = WorkerPool(plan, feature_weights, max_attempts)
        try:
            yield from _stream(ray, pool, reqs)
        finally:
            pool.close()
    finally:
        if connected:
            ray.shutdown()


def _stream(ray, pool: WorkerPool, reqs: list[EstimateRequest]) -> Iterator[EstimateResult]:
    meshes: dict[tuple[str, str], tuple[object, list]] = {}  # mesh key -> (ObjectMesh, [ref])

    def submit(actor, index, req: EstimateRequest):
        key = (str(Path(req.mesh).resolve()), req.mesh_units)
        if key not in meshes:
            mesh = load_mesh(req.mesh, req.mesh_units)
            meshes[key] = (mesh, [ray.put(mesh)])
        image = load_rgb(req.image) if isinstance(req.image, (str, Path)) else check_rgb(req.image)
        prepared = _prepare(req, image, meshes[key][0])
        refs = {"image": [ray.put(image)], "meshes": {key: meshes[key][1]}}
        return actor.run_request.remote(prepared, refs)

    for index, reply, attempts in pool.run(enumerate(reqs), submit):
        rid = reqs[index].id if reqs[index].id is not None else index
        yield EstimateResult(rid, index, reply.value, reply.failure, attempts, reply.worker, reply.seconds)
