"""Scale out on Ray (optional: `pip install -e '.[ray]'`; docs/distributed.md).

- `estimate_many(requests, address=None)`: single-image searches for a pipeline, on Ray workers (one per
  GPU, or per CPU slot), streamed as each finishes.
- `python -m perch_warp eval ... --ray [ADDRESS]`: an evaluation's targets on Ray workers
  (perch_warp.distributed.eval_runner); the driver alone writes the outputs, as in a serial run.

Ray is imported only when a cluster is used, so this package imports without it.
"""

from .api import EstimateRequest, EstimateResult, estimate_many
from .cluster import INSTALL_HINT, WorkerPlan, plan_workers, require_ray

__all__ = [
    "INSTALL_HINT",
    "EstimateRequest",
    "EstimateResult",
    "WorkerPlan",
    "estimate_many",
    "plan_workers",
    "require_ray",
]
