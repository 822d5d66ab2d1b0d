"""A fixed set of Ray worker actors fed from a queue of tasks, with the fault handling of issue 20.

- A worker lost mid-task (killed, out of memory, its node lost: a Ray error on the task's reference)
  is replaced by a new worker, and the task goes back to the front of the queue, to the next free
  worker; a task that has lost its worker `max_attempts` times is given up with that reason (a task
  that kills every worker it meets is not retried forever).
- A task that fails inside the worker returns its failure as its reply (worker.Reply): deterministic,
  never retried.
- Every task gets exactly one reply: the pool keeps one reference per task in flight and forgets it
  when that reply (or the loss) comes back.
"""

from __future__ import annotations

import sys
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from ..errors import PerchError
from ..eval.protocol import failure_reason
from .cluster import WorkerPlan, require_ray
from .worker import Reply, SearchWorker

DEFAULT_MAX_ATTEMPTS = 3
STARTUP_TIMEOUT_S = 600.0  # a worker imports Warp and torch first: tens of seconds on a loaded machine


@dataclass
class _Task:
    key: Hashable
    payload: Any
    attempt: int = 1


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def worker_lost_errors(ray) -> tuple[type[BaseException], ...]:
    """Ray's errors that mean the worker (or its node, or the task's result) was lost, not that the task
    failed: these are retried on another worker."""
    ex = ray.exceptions
    return (ex.RayActorError, ex.WorkerCrashedError, ex.NodeDiedError, ex.OutOfMemoryError, ex.ObjectLostError)


class WorkerPool:
    """`plan.n_workers` SearchWorker actors holding the `weights` (put in the object store once)."""

    def __init__(
        self,
        plan: WorkerPlan,
        weights,
        max_attempts: int = DEFAULT_MAX_ATTEMPTS,
        max_losses: int | None = None,
        *,
        ray=None,
        worker_cls: type = SearchWorker,
    ):
        """`ray` and `worker_cls` default to Ray and SearchWorker (the tests pass stand-ins)."""
        if max_attempts < 1:
            raise PerchError(f"max_attempts must be at least 1, got {max_attempts}")
        self.ray = ray or require_ray()
        self.plan = plan
        self.max_attempts = max_attempts
        # Replacements in all: beyond this many lost workers, something kills every worker (e.g. a
        # worker that cannot start on this cluster) and the run stops instead of looping.
        self.max_losses = 2 * plan.n_workers + 2 * max_attempts if max_losses is None else max_losses
        self.losses = 0
        self.retries = 0
        self._weights_ref = self.ray.put(weights)
        # max_restarts=0: a lost worker is replaced by this pool (which knows its task), not by Ray.
        self._cls = self.ray.remote(
            num_cpus=plan.cpus_per_worker, num_gpus=plan.gpus_per_worker, max_restarts=0, max_task_retries=0
        )(worker_cls)
        self.actors = [self._new_actor() for _ in range(plan.n_workers)]
        self._in_flight: dict[Any, tuple[Any, _Task]] = {}  # task reference -> (worker, task)
        # Replacements still importing (ping reference -> worker): a retried task goes to whichever worker
        # is free first, not to a new one that may take tens of seconds to start.
        self._starting: dict[Any, Any] = {}
        self._wait_started()

    def _new_actor(self):
        return self._cls.remote(self.plan.device, self.plan.cpus_per_worker, [self._weights_ref])

    def _wait_started(self) -> None:
        """Every worker answers once its imports are done; one that cannot start is an error naming why."""
        refs = [a.ping.remote() for a in self.actors]
        ready, pending = self.ray.wait(refs, num_returns=len(refs), timeout=STARTUP_TIMEOUT_S)
        if pending:
            raise PerchError(
                f"{len(pending)} of {len(refs)} Ray workers did not start within {STARTUP_TIMEOUT_S:.0f} s "
                f"(the cluster has {self.ray.cluster_resources()}): ask for fewer --ray-workers"
            )
        try:
            self.names = self.ray.get(ready)
        except self.ray.exceptions.RayError as e:
            raise PerchError(f"a Ray worker could not start: {_first_line(e)}") from None

    def busy(self) -> dict[Hashable, Any]:
        """Task key -> the worker actor running it (for monitoring; tests kill one mid-task)."""
        return {task.key: actor for actor, task in self._in_flight.values()}

    def run(
        self, tasks: Iterable[tuple[Hashable, Any]], submit: Callable[[Any, Hashable, Any], Any]
    ) -> Iterator[tuple[Hashable, Reply, int]]:
        """(key, reply, attempts) for every (key, payload) of `tasks`, as they finish (any order).
        `submit(worker, key, payload)` starts the task on a worker and returns its reference; what it
        raises is the task's failure (it did not start: nothing to retry)."""
        source = iter(tasks)
        retry: deque[_Task] = deque()
        idle = list(self.actors)
        out: deque[tuple[Hashable, Reply, int]] = deque()
        while True:
            # Keep every worker busy (retried tasks first) before handing a reply over: the caller's
            # bookkeeping then overlaps the workers' searches.
            while idle:
                task = retry.popleft() if retry else _next_task(source)
                if task is None:
                    break
                self._start(idle, task, submit, out)
            while out:
                yield out.popleft()
            if not self._in_flight:
                if idle:  # the loop above found no task left: done
                    return
                if not self._starting:
                    raise PerchError(
                        f"all Ray workers were lost ({self.losses} losses); what finished is saved, run again "
                        "to continue"
                    )
            [ref], _ = self.ray.wait([*self._in_flight, *self._starting], num_returns=1)
            if ref in self._starting:
                self._started(ref, idle)
                continue
            actor, task = self._in_flight.pop(ref)
            self._collect(ref, actor, task, idle, retry, out)

    def _start(self, idle: list, task: _Task, submit, out: deque) -> None:
        """Start `task` on an idle worker; its failure reply goes to `out` when `submit` raises."""
        actor = idle.pop()
        try:
            ref = submit(actor, task.key, task.payload)
        except Exception as e:  # noqa: BLE001 - a task that cannot start fails with its reason
            idle.append(actor)
            out.append((task.key, Reply(failure=failure_reason(e)), task.attempt))
            return
        self._in_flight[ref] = (actor, task)

    def _collect(self, ref, actor, task: _Task, idle: list, retry: deque, out: deque) -> None:
        """The finished task's (key, reply, attempts) to `out`; to `retry` when its worker was lost."""
        try:
            reply = self.ray.get(ref)
        except worker_lost_errors(self.ray) as e:
            self._replace(actor, f"worker lost on task {task.key}: {_first_line(e)}")
            if task.attempt >= self.max_attempts:
                reason = f"its worker was lost {task.attempt} times (last: {_first_line(e)})"
                out.append((task.key, Reply(failure=reason), task.attempt))
                return
            self.retries += 1
            _log(f"task {task.key}: worker lost, retrying on another worker (attempt {task.attempt + 1})")
            retry.appendleft(_Task(task.key, task.payload, task.attempt + 1))
            return
        except self.ray.exceptions.RayTaskError as e:  # raised by the worker's method itself: deterministic
            idle.append(actor)
            cause = e.cause if isinstance(getattr(e, "cause", None), BaseException) else e
            out.append((task.key, Reply(failure=f"worker error: {failure_reason(cause)}"), task.attempt))
            return
        idle.append(actor)
        out.append((task.key, reply, task.attempt))

    def _replace(self, actor, why: str) -> None:
        """Drop a lost worker and start another in its place while the loss budget lasts."""
        self.actors.remove(actor)
        self.losses += 1
        _log(why)
        if self.losses <= self.max_losses:
            new = self._new_actor()
            self.actors.append(new)
            self._starting[new.ping.remote()] = new

    def _started(self, ref, idle: list) -> None:
        """A replacement answered: it joins the idle workers (or, if it could not start, is replaced)."""
        actor = self._starting.pop(ref)
        try:
            self.ray.get(ref)
        except self.ray.exceptions.RayError as e:
            self._replace(actor, f"a replacement worker could not start: {_first_line(e)}")
            return
        idle.append(actor)

    def close(self) -> None:
        """End the workers (their engines with them)."""
        for actor in self.actors:
            self.ray.kill(actor)
        self.actors = []


def _next_task(source: Iterator) -> _Task | None:
    item = next(source, None)
    return None if item is None else _Task(item[0], item[1])


def _first_line(e: BaseException) -> str:
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    return lines[0] if lines else type(e).__name__
