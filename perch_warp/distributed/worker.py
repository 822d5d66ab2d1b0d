"""The Ray worker: one process per GPU (or CPU slot) that keeps its built engines between targets.

`SearchWorker` is a plain class, made a Ray actor by the pool (`ray.remote(...)(SearchWorker)`), so this
module imports without Ray. Everything it needs comes from the driver through Ray's object store (the
weights, each mesh, each photo), so a worker node needs the package, not the dataset or ../shared.

A failure inside a search is returned as the target's reason (`Reply.failure`), never raised: it is
deterministic (the same inputs fail again), so the driver records it once and retries nothing. Only the
loss of the worker itself (killed, out of memory, node lost) reaches the driver as a Ray error, and only
that is retried on another worker.
"""

from __future__ import annotations

import dataclasses
import os
import socket
import time
from dataclasses import dataclass
from typing import Any

from ..eval.protocol import EngineEstimator, Job, RestSpec, failure_reason, run_job, stops_the_run


@dataclass
class Reply:
    """What a worker returns for one task: the value (a Done, or a Result) or the failure's one-line reason.
    `stops` marks a failure that would fail every task alike (an option problem), which ends the run."""

    value: Any = None
    failure: str | None = None
    stops: bool = False
    worker: str = ""  # host:pid, for the record
    seconds: float = 0.0  # the call's wall time in the worker, engine build included


def limit_threads(n: int) -> None:
    """One worker per `n` CPU slots: its torch (intra-op) and OpenMP/BLAS pools get `n` threads, so workers
    sharing a machine do not oversubscribe its cores (Ray sets OMP_NUM_THREADS too; torch may be imported
    already, so it is set directly)."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(n)
    import torch

    torch.set_num_threads(n)


class SearchWorker:
    """Engines per (object, configuration), built on first use and kept: kernel builds and mesh uploads
    are paid once per worker. `weights_ref` is a one-element list holding the object-store reference of
    the FeatureWeights (a list, so that Ray hands it over unresolved: it is fetched once, here)."""

    def __init__(self, device: str, cpus: int, weights_ref: list):
        limit_threads(cpus)
        self.device = device
        self.cpus = cpus
        self._weights_ref = weights_ref[0]
        self._weights = None
        self._meshes: dict[Any, Any] = {}  # mesh key -> ObjectMesh
        self._estimators: dict[Any, EngineEstimator] = {}  # (EngineConfig, RestSpec) -> estimator (engines by mesh key)
        self.name = f"{socket.gethostname()}:{os.getpid()}"

    def ping(self) -> str:
        """The worker's name, once it has started (its imports done)."""
        return self.name

    def _estimator(self, config, mesh_refs: dict, rest: RestSpec = RestSpec()) -> EngineEstimator:
        """The estimator for `config` and `rest`, whose engines load their meshes from `mesh_refs` (key -> [ref])."""
        import ray

        if self._weights is None:
            self._weights = ray.get(self._weights_ref)
        if self.device == "cpu" and config.cpu_threads is None:
            # "One thread per core" would count the whole machine's cores: this worker has `cpus` of them.
            config = dataclasses.replace(config, cpu_threads=self.cpus)
        key = (config, rest)
        if key not in self._estimators:
            self._estimators[key] = EngineEstimator(
                {}, device=self.device, config=config, rest=rest, weights=self._weights
            )
        est = self._estimators[key]
        # A mesh not yet loaded is fetched from this call's references (the driver sends them with every task).
        est.load_mesh = lambda key: self._mesh(key, mesh_refs)
        return est

    def _mesh(self, key, mesh_refs: dict):
        import ray

        if key not in self._meshes:
            self._meshes[key] = ray.get(mesh_refs[key][0])
        return self._meshes[key]

    def run_target(self, job: Job, config, refs: dict, rest: RestSpec = RestSpec()) -> Reply:
        """One eval target: `refs` = {"image": [ref], "meshes": {obj_id: [ref]}}; its Done, or its failure."""
        import ray

        t0 = time.perf_counter()
        try:
            image = ray.get(refs["image"][0])
            done = run_job(job, image, self._estimator(config, refs["meshes"], rest))
            return Reply(value=done, worker=self.name, seconds=time.perf_counter() - t0)
        except Exception as e:  # noqa: BLE001 - a target's failure is its reply; see the module doc
            return Reply(None, failure_reason(e), stops_the_run(e), self.name, time.perf_counter() - t0)

    def run_request(self, request, refs: dict) -> Reply:
        """One estimate_many request (perch_warp.distributed.api.Prepared): its Result, or its failure."""
        import ray

        t0 = time.perf_counter()
        try:
            image = ray.get(refs["image"][0])
            engine = self._estimator(request.config, refs["meshes"]).engine(request.mesh_key)
            result = engine.estimate(image, request.camera, request.table, request.resting, request.space)
            return Reply(value=result, worker=self.name, seconds=time.perf_counter() - t0)
        except Exception as e:  # noqa: BLE001 - a request's failure is its reply; see the module doc
            return Reply(None, failure_reason(e), stops_the_run(e), self.name, time.perf_counter() - t0)
