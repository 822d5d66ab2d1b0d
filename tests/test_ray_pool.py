"""WorkerPool's fault handling against a stand-in for Ray (no cluster, no Ray needed): every task
answered exactly once, a lost worker's task retried on another one up to the bound, failures not retried."""

from __future__ import annotations

import types

import pytest

from perch_warp.distributed.cluster import WorkerPlan
from perch_warp.distributed.pool import WorkerPool
from perch_warp.distributed.worker import Reply
from perch_warp.errors import PerchError


class ActorDied(Exception):
    pass


class TaskError(Exception):
    pass


class Ref:
    def __init__(self, value=None, error=None):
        self.value, self.error = value, error


class FakeRay:
    """Tasks run at once when submitted; a reference holds the value or the error. `deaths[key]`: how many
    times the worker running `key` dies on it."""

    exceptions = types.SimpleNamespace(
        RayActorError=ActorDied, WorkerCrashedError=ActorDied, NodeDiedError=ActorDied,
        OutOfMemoryError=ActorDied, ObjectLostError=ActorDied, RayTaskError=TaskError, RayError=Exception,
    )  # fmt: skip

    def __init__(self, deaths: dict):
        self.deaths, self.started, self.killed = dict(deaths), 0, 0

    def put(self, x):
        return Ref(x)

    def remote(self, **options):
        fake = self

        def wrap(cls):
            class Handle:
                def __init__(self, *args):
                    fake.started += 1
                    self.obj, self.dead = cls(*args), False

                def __getattr__(self, name):
                    handle = self

                    def call(*a):
                        if handle.dead:
                            return Ref(error=ActorDied("the actor died"))
                        try:
                            return Ref(getattr(handle.obj, name)(*a))
                        except ActorDied as e:
                            handle.dead = True
                            return Ref(error=e)

                    return types.SimpleNamespace(remote=call)

            return types.SimpleNamespace(remote=lambda *a: Handle(*a))

        return wrap

    def wait(self, refs, num_returns=1, timeout=None):
        return refs[:num_returns], refs[num_returns:]

    def get(self, ref):
        if isinstance(ref, list):
            return [self.get(r) for r in ref]
        if ref.error is not None:
            raise ref.error
        return ref.value

    def kill(self, handle):
        self.killed += 1

    def cluster_resources(self):
        return {"CPU": 2.0}


def make_worker(fake: FakeRay):
    class Worker:
        def __init__(self, device, cpus, weights_ref):
            pass

        def ping(self):
            return "w"

        def run(self, key):
            if fake.deaths.get(key, 0) > 0:
                fake.deaths[key] -= 1
                raise ActorDied(f"killed on {key}")
            if key == "bad":
                return Reply(failure="deterministic")
            return Reply(value=key * 2)

    return Worker


def run_pool(deaths: dict, keys: list, max_attempts: int = 3, max_losses: int | None = None):
    fake = FakeRay(deaths)
    pool = WorkerPool(
        WorkerPlan(2, 1, 0, "cpu"), None, max_attempts, max_losses, ray=fake, worker_cls=make_worker(fake)
    )
    replies = list(pool.run(((k, k) for k in keys), lambda actor, key, payload: actor.run.remote(payload)))
    pool.close()
    return fake, pool, replies


def test_every_task_is_answered_once_and_a_lost_worker_is_replaced():
    fake, pool, replies = run_pool({3: 1}, list(range(6)))
    assert sorted(k for k, _, _ in replies) == list(range(6))
    by_key = {k: (r, n) for k, r, n in replies}
    assert by_key[3] == (Reply(value=6), 2) and all(by_key[k][1] == 1 for k in (0, 1, 2, 4, 5))
    assert pool.losses == 1 and pool.retries == 1 and fake.started == 3  # 2 workers, 1 replacement


def test_a_task_that_kills_every_worker_gives_up_after_the_bound():
    fake, pool, replies = run_pool({1: 10}, [0, 1, 2], max_attempts=3)
    r, attempts = {k: (r, n) for k, r, n in replies}[1]
    assert attempts == 3 and "its worker was lost 3 times" in r.failure and len(replies) == 3
    assert pool.losses == 3 and fake.deaths[1] == 7  # tried exactly three times


def test_a_deterministic_failure_is_not_retried():
    _, pool, replies = run_pool({}, [0, "bad", 2])
    assert ("bad", Reply(failure="deterministic"), 1) in replies and pool.retries == 0


def test_when_every_worker_is_lost_the_run_stops_saying_so():
    with pytest.raises(PerchError, match=r"all Ray workers were lost \(2 losses\)"):
        run_pool({0: 5, 1: 5}, [0, 1, 2], max_losses=0)
