"""`eval --ray` and perch_warp.distributed on a local Ray cluster of 2 CPU slots (issue 20).

The searches are real and tiny: object 1 (the master chef can) in the shared frames of scenes 2, 48
and 51 (3 targets, 3 photos), a 0.1 m square at 5 cm and 90 deg on the photo at quarter scale, not
refined, so each takes about a second once a worker has built its engine. Every test shares one Ray
cluster (module fixture) and compares with one serial run."""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np
import pytest
from _procs import sigkill_once_written

from perch_warp import bop
from perch_warp.distributed import cluster
from perch_warp.errors import PerchError
from perch_warp.eval import command, protocol
from perch_warp.options import engine_config_from_args, search_space_from_args

EVAL_ARGS = [
    "--device", "cpu", "--clip", "0.1", "--xy-step", "0.05", "--yaw-step", "90", "--refine-xy", "0.05",
    "--refine-yaw", "90", "--no-refine", "--image-scale", "0.25", "--search", "exhaustive", "--weights", "caffe",
]  # fmt: skip
SCENES, OBJECTS = [2, 48, 51], [1]


def _args(dataset, out, *extra):
    p = argparse.ArgumentParser()
    command.add_arguments(p)
    return p.parse_args(["--dataset", str(dataset), "--out", str(out), *EVAL_ARGS, *extra])


def _eval(dataset, out, runner=None, space_fn=None, rest=protocol.RestSpec(), scenes=SCENES, **kw):
    """evaluate() as `eval` runs it with EVAL_ARGS: serial unless a runner is given."""
    args = _args(dataset, out)
    config = engine_config_from_args(args)
    space_fn = space_fn or (lambda camera, table, resting: search_space_from_args(args, camera, table))
    make = None if runner else (lambda paths: protocol.EngineEstimator(paths, args.weights, args.device, config, rest))
    return protocol.evaluate(
        dataset, out, make_estimator=make, runner=runner, space_fn=space_fn, scenes=scenes, objects=OBJECTS,
        progress=False, plots=False, options={"test": "distributed", "rest": rest.mode}, **kw,
    )  # fmt: skip


def _ray_runner(dataset, on_outcome=None, rest=protocol.RestSpec()):
    from perch_warp.distributed.eval_runner import RayOptions, ray_runner

    args = _args(dataset, "unused")
    config = engine_config_from_args(args)
    return ray_runner(RayOptions(n_workers=2), args.weights, "cpu", config, on_outcome, rest)


def _journal(out) -> list[dict]:
    return [json.loads(x) for x in (out / "targets.jsonl").read_text().splitlines()]


def _rows(out) -> list[tuple]:
    """results.csv without its time column, in file order."""
    return [(r.scene_id, r.im_id, r.obj_id, r.score, r.R.tolist(), r.t_mm.tolist()) for r in bop.read_results(out)]


# ----------------------------------------------------------------------------- without a cluster


def test_ray_missing_says_how_to_install_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    from perch_warp.cli import main

    root = tmp_path / "ds"
    root.mkdir()
    assert main(["eval", "--dataset", str(root), "--out", str(tmp_path / "out"), "--ray"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "pip install -e '.[ray]'" in err


def test_eval_ray_hands_the_resting_pose_mode_to_the_workers(tmp_path, monkeypatch, capsys):
    """`eval --ray --rest stable --roll-step 45` builds the Ray runner for those stable poses."""
    pytest.importorskip("ray")
    from perch_warp.cli import main
    from perch_warp.distributed import eval_runner

    seen = []

    def fake_runner(options, weights_spec, device, config, on_outcome=None, rest=protocol.RestSpec()):
        seen.append(rest)
        raise PerchError("stopped by the test")

    monkeypatch.setattr(eval_runner, "ray_runner", fake_runner)
    root = tmp_path / "ds"
    root.mkdir()
    argv = ["eval", "--dataset", str(root), "--out", str(tmp_path / "out"), "--ray"]
    assert main([*argv, "--rest", "stable", "--roll-step", "45"]) == 1
    assert main(argv) == 1
    assert "stopped by the test" in capsys.readouterr().err
    assert seen == [protocol.RestSpec("stable", 45.0), protocol.RestSpec("truth", protocol.RestSpec().roll_step_deg)]


def test_worker_plan_follows_the_cluster():
    assert cluster.plan_workers({"CPU": 2.0}, None) == cluster.WorkerPlan(2, 1, 0, "cpu")
    assert cluster.plan_workers({"CPU": 16.0, "GPU": 2.0}, None) == cluster.WorkerPlan(2, 1, 1, "cuda:0")
    assert cluster.plan_workers({"CPU": 16.0, "GPU": 2.0}, "cpu", cpus_per_worker=4).n_workers == 4
    with pytest.raises(PerchError, match="asks for GPUs, but the Ray cluster has none"):
        cluster.plan_workers({"CPU": 8.0}, "cuda:0")
    with pytest.raises(PerchError, match="--ray-workers 3: the Ray cluster holds only 2 workers"):
        cluster.plan_workers({"CPU": 2.0}, "cpu", n_workers=3)


# ----------------------------------------------------------------------------- on a local cluster


@pytest.fixture(scope="module")
def ray_cluster():
    """A local cluster of 2 CPU slots, shared by this module's tests (the runners reuse the connection)."""
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install -e '.[ray]')")
    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def serial(shared, tmp_path_factory, caffe_weights):
    """The serial run every distributed one is compared with."""
    out = tmp_path_factory.mktemp("serial")
    summary = _eval(shared / "data" / "ycbv", out)
    assert summary["n_evaluated"] == 3 and summary["n_failed"] == 0
    return out


@pytest.mark.ray
def test_distributed_results_equal_the_serial_ones(ray_cluster, serial, shared, tmp_path):
    s = _eval(shared / "data" / "ycbv", tmp_path, runner=_ray_runner(shared / "data" / "ycbv"))
    assert s["n_evaluated"] == 3 and s["n_failed"] == 0
    assert _rows(tmp_path / "results.csv") == _rows(serial / "results.csv")  # same poses, scores, order
    workers = {j["details"]["worker"]["name"] for j in _journal(tmp_path)}
    assert len(workers) == 2  # both workers searched
    # Resumable either way: a serial rerun on the distributed OUTDIR has nothing left to do.
    again = _eval(shared / "data" / "ycbv", tmp_path)
    assert again["n_evaluated"] == 3 and len(_journal(tmp_path)) == 3


@pytest.mark.ray
def test_distributed_stable_rests_equal_the_serial_ones(ray_cluster, shared, tmp_path):
    """--rest stable on the workers: every stable pose of the can searched there, as in this process."""
    data, stable = shared / "data" / "ycbv", protocol.RestSpec("stable", roll_step_deg=90.0)
    s = _eval(data, tmp_path / "serial", rest=stable, scenes=[2, 51])
    d = _eval(data, tmp_path / "ray", runner=_ray_runner(data, rest=stable), rest=stable, scenes=[2, 51])
    assert s["n_evaluated"] == d["n_evaluated"] == 2 and s["n_failed"] == d["n_failed"] == 0
    assert _rows(tmp_path / "ray" / "results.csv") == _rows(tmp_path / "serial" / "results.csv")
    # Per target: the workers' journal lists targets as they finish, not in the serial run's order.
    won = {
        tuple(j["details"]["rest"] for j in sorted(_journal(tmp_path / run), key=lambda j: (j["scene_id"], j["im_id"])))
        for run in ("serial", "ray")
    }
    assert len(won) == 1  # the same resting pose won each target, named in each journal
    labels = [j["details"]["rest"] for j in _journal(tmp_path / "ray")]
    assert all(isinstance(label, str) and label for label in labels)


@pytest.mark.ray
def test_a_worker_killed_mid_target_is_replaced_and_every_target_done_once(ray_cluster, serial, shared, tmp_path):
    killed = []

    def kill_the_newest(pool, target):
        # Called as soon as the first outcome is in: the pool has just started the next target on the
        # freed worker, so that worker is mid-target.
        if not killed:
            key, actor = list(pool.busy().items())[-1]
            killed.append(key)
            ray_cluster.kill(actor)

    s = _eval(shared / "data" / "ycbv", tmp_path, runner=_ray_runner(shared / "data" / "ycbv", kill_the_newest))
    journal = _journal(tmp_path)
    assert sorted((j["scene_id"], j["im_id"], j["inst"]) for j in journal) == sorted(
        (r[0], r[1], 0) for r in _rows(serial / "results.csv")
    )  # each target exactly once
    assert s["n_evaluated"] == 3 and s["n_failed"] == 0 and killed
    retried = [j for j in journal if j["details"]["worker"]["attempts"] > 1]
    assert [(j["scene_id"], j["im_id"], j["inst"]) for j in retried] == killed
    assert _rows(tmp_path / "results.csv") == _rows(serial / "results.csv")


@pytest.mark.ray
def test_an_interrupted_driver_resumes_without_repeating_finished_targets(ray_cluster, serial, shared, tmp_path):
    def interrupt(pool, target):
        raise KeyboardInterrupt  # the driver stops after its first journalled target, another one in flight

    with pytest.raises(KeyboardInterrupt):
        _eval(shared / "data" / "ycbv", tmp_path, runner=_ray_runner(shared / "data" / "ycbv", interrupt))
    first = _journal(tmp_path)
    assert len(first) == 1 and len(bop.read_results(tmp_path / "results.csv")) == 1
    s = _eval(shared / "data" / "ycbv", tmp_path, runner=_ray_runner(shared / "data" / "ycbv"))
    journal = _journal(tmp_path)
    keys = [(j["scene_id"], j["im_id"], j["inst"]) for j in journal]
    assert len(journal) == 3 and len(set(keys)) == 3 and journal[0] == first[0]
    assert s["n_evaluated"] == 3 and _rows(tmp_path / "results.csv") == _rows(serial / "results.csv")


@pytest.mark.ray
def test_a_deterministic_failure_is_recorded_once_and_not_retried(ray_cluster, shared, tmp_path, capsys):
    from perch_warp.search_space import SearchSpace

    def far_away(camera, table, resting):  # a region the camera cannot see: the search fails in the worker
        return SearchSpace((50.0, 50.1), (50.0, 50.1), 0.05, (0.0, 2 * math.pi), math.radians(90))

    s = _eval(shared / "data" / "ycbv", tmp_path, runner=_ray_runner(shared / "data" / "ycbv"), space_fn=far_away)
    journal = _journal(tmp_path)
    assert (
        s["n_failed"] == 3 and len(journal) == 3 and all("projects outside the image" in j["failed"] for j in journal)
    )
    assert "retrying" not in capsys.readouterr().err


@pytest.mark.ray
def test_estimate_many_streams_results_and_failures(ray_cluster, shared, caffe_weights):
    from perch_warp import Engine, EngineConfig, load_mesh, load_rgb
    from perch_warp.bop.inout import read_camera_json
    from perch_warp.camera import camera_from_entry
    from perch_warp.distributed import EstimateRequest, estimate_many
    from perch_warp.search_space import SearchSpace
    from perch_warp.table import RestingPose, Table

    d = shared / "data" / "ycbv" / "test" / "000002"
    mesh_path = shared / "data" / "ycbv" / "models" / "obj_000009.obj"
    entry = read_camera_json(d / "scene_camera.json", 1)
    config = EngineConfig(image_scale=0.25, refine=False, search="exhaustive", cpu_threads=1)
    space = SearchSpace((-0.05, 0.05), (-0.2, -0.1), 0.05, (0.0, 2 * math.pi), math.radians(90))
    far = SearchSpace((50.0, 50.1), (50.0, 50.1), 0.05, (0.0, 2 * math.pi), math.radians(90))
    reqs = [
        EstimateRequest(d / "rgb" / "000001.png", entry, mesh_path, space=space, config=config, id="near"),
        EstimateRequest(d / "rgb" / "000001.png", entry, mesh_path, space=far, config=config, id="far"),
    ]
    got = {r.id: r for r in estimate_many(reqs, weights="caffe")}
    assert set(got) == {"near", "far"} and got["near"].ok and got["far"].attempts == 1
    assert "projects outside the image" in got["far"].error
    mesh, image = load_mesh(mesh_path), load_rgb(d / "rgb" / "000001.png")
    camera = camera_from_entry(entry, image.shape[1], image.shape[0])
    table = Table.from_entry(entry)
    want = Engine(mesh, caffe_weights, "cpu", config).estimate(
        image, camera, table, RestingPose.upright(mesh.vertices_m), space
    )
    np.testing.assert_array_equal(got["near"].result.T_m2c, want.T_m2c)
    assert got["near"].result.score == want.score


@pytest.mark.ray
def test_a_driver_killed_with_sigkill_resumes_without_repeating_finished_targets(serial, shared, tmp_path):
    """`eval --ray` in its own process (its own local cluster) killed with SIGKILL once a target is journalled:
    the same command rerun does only what is left, and the results equal the serial run's."""
    import subprocess

    dataset = shared / "data" / "ycbv"
    cmd = [sys.executable, "-m", "perch_warp", "eval", "--dataset", str(dataset), "--out", str(tmp_path), *EVAL_ARGS]
    cmd += ["--scenes", *map(str, SCENES), "--objects", *map(str, OBJECTS), "--no-plots", "--ray", "--ray-workers", "1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    sigkill_once_written(proc, tmp_path / "targets.jsonl", 1, 600, group=True)
    first = _journal(tmp_path)
    assert 1 <= len(first) < 3
    subprocess.run(cmd, check=True, timeout=600, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # the rerun
    journal_rows = _journal(tmp_path)
    keys = [(j["scene_id"], j["im_id"], j["inst"]) for j in journal_rows]
    assert len(journal_rows) == 3 and len(set(keys)) == 3 and journal_rows[: len(first)] == first
    assert _rows(tmp_path / "results.csv") == _rows(serial / "results.csv")
