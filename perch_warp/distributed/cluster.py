"""Ray, optional: importing it with a one-line hint, joining or starting a cluster, and sizing the workers.

Workers are Ray actors (perch_warp.distributed.worker), one per GPU when the cluster has GPUs (Ray sets
each actor's CUDA_VISIBLE_DEVICES, so inside it the GPU is `cuda:0`), else one per `cpus_per_worker`
CPUs of the cluster."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import PerchError

INSTALL_HINT = "pip install -e '.[ray]'"


def require_ray():
    """The `ray` module, or a PerchError saying in one line how to install it."""
    try:
        import ray
    except ImportError:
        raise PerchError(f"--ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def connect(address: str | None = None, num_cpus: int | None = None) -> bool:
    """Join the Ray cluster at `address` ("auto": the one `ray start` made on this machine), or start a
    local one on this machine (`num_cpus`: its CPU slots, default all cores) when `address` is None;
    reuse the connection when this process already has one. True when this call connected (so the
    caller disconnects when done)."""
    ray = require_ray()
    if ray.is_initialized():
        return False
    kw = {"include_dashboard": False, "log_to_driver": True, "configure_logging": False}
    try:
        if address is None:
            ray.init(num_cpus=num_cpus, **kw)
        else:
            ray.init(address=address, **kw)
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = f"at {address}" if address else "on this machine"
        raise PerchError(f"could not start or join a Ray cluster {where}: {' '.join(str(e).split())}") from None
    return True


@dataclass(frozen=True)
class WorkerPlan:
    """How many workers, what each holds, and the Warp device each searches on."""

    n_workers: int
    cpus_per_worker: int
    gpus_per_worker: int  # 0 or 1
    device: str  # inside a worker: "cpu" or "cuda:0" (its own GPU)

    def describe(self) -> str:
        per = f"{self.cpus_per_worker} CPU" + (f" + {self.gpus_per_worker} GPU" if self.gpus_per_worker else "")
        return f"{self.n_workers} Ray workers ({per} each, device {self.device})"


def plan_workers(
    resources: dict, device: str | None, n_workers: int | None = None, cpus_per_worker: int = 1
) -> WorkerPlan:
    """The workers for a cluster's `resources` (ray.cluster_resources()): one per GPU when it has GPUs and
    `device` is not "cpu" (a CUDA device asked for on a cluster without GPUs is an error), else one per
    `cpus_per_worker` CPUs; `n_workers` caps the count (more than the resources hold is refused, since
    those workers would wait forever)."""
    if cpus_per_worker < 1:
        raise PerchError(f"--ray-cpus-per-worker must be at least 1, got {cpus_per_worker}")
    if n_workers is not None and n_workers < 1:
        raise PerchError(f"--ray-workers must be at least 1, got {n_workers}")
    gpus = int(math.floor(resources.get("GPU", 0)))
    cpus = int(math.floor(resources.get("CPU", 0)))
    want_gpu = (device is None and gpus > 0) or (device or "").startswith("cuda")
    if want_gpu and gpus == 0:
        raise PerchError(f"--device {device} asks for GPUs, but the Ray cluster has none ({cpus} CPUs)")
    if device not in (None, "cpu") and not (device or "").startswith("cuda"):
        raise PerchError(f"--device {device!r} is neither cpu nor cuda[:N]")
    # A GPU worker still needs a CPU slot for its host stages; cap by both.
    slots = min(gpus, cpus // cpus_per_worker) if want_gpu else cpus // cpus_per_worker
    if slots < 1:
        raise PerchError(
            f"the Ray cluster has {cpus} CPUs and {gpus} GPUs: not enough for one worker of "
            f"{cpus_per_worker} CPUs{' and 1 GPU' if want_gpu else ''}"
        )
    if n_workers is not None and n_workers > slots:
        raise PerchError(
            f"--ray-workers {n_workers}: the Ray cluster holds only {slots} workers of {cpus_per_worker} CPUs"
            f"{' and 1 GPU' if want_gpu else ''} ({cpus} CPUs, {gpus} GPUs)"
        )
    return WorkerPlan(n_workers or slots, cpus_per_worker, 1 if want_gpu else 0, "cuda:0" if want_gpu else "cpu")
