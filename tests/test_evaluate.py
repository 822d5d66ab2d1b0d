"""The eval loop with a fake estimator: metrics against an independent computation, resume, outputs."""

from __future__ import annotations

import argparse
import csv
import json
import math

import numpy as np
import pytest
from test_bop import K, write_tiny_dataset

from perch_warp import bop
from perch_warp.errors import PerchError
from perch_warp.eval import command, protocol
from perch_warp.mesh import load_mesh
from perch_warp.table import decompose_on_table, model_to_camera

# Fake estimates: the ground truth moved on the table by (dx, 0) metres and turned by dyaw, per target.
OFFSETS = {
    (1, 1, 0): (0.0, 0.0),
    (1, 1, 1): (0.015, 0.4),
    (1, 1, 3): (0.05, 0.0),
    (1, 2, 0): (0.004, 1.0),
    (1, 2, 1): (0.12, 0.0),
}


class FakeEstimator:
    def __init__(self, fail_after: int | None = None):
        self.calls = []
        self.fail_after = fail_after

    def __call__(self, target, image, camera, table, resting, space):
        if self.fail_after is not None and len(self.calls) >= self.fail_after:
            raise KeyboardInterrupt
        assert image.shape == (camera.height, camera.width, 3) and image.dtype == np.uint8
        self.calls.append(target.key)
        _, x, y, yaw = decompose_on_table(table, target.R_gt, target.t_gt_m)
        dx, dyaw = OFFSETS[target.key]
        R, t = model_to_camera(table, resting, x + dx, y, yaw + dyaw)
        return protocol.Estimate(R, t, 1.0 - dx, {"fake": True})


def run_eval(root, out, est, **kw):
    kw.setdefault("plots", False)
    return protocol.evaluate(
        root, out, make_estimator=lambda paths: est, space_fn=protocol.visible_table_space(0.02), progress=False, **kw
    )


def brute_adds(R_e, t_e, R_g, t_g, pts):
    pe = pts @ R_e.T + t_e
    pg = pts @ R_g.T + t_g
    return np.linalg.norm(pg[:, None] - pe[None], axis=2).min(axis=1).mean()


def test_metrics_agree_with_an_independent_computation(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    est = FakeEstimator()
    s = run_eval(root, tmp_path / "out", est)
    assert sorted(est.calls) == sorted(OFFSETS)
    assert s["skipped_no_model"] == {"7": 1} and s["n_targets"] == 5
    # Independent ADD-S: brute-force nearest neighbours on the mesh vertices (few, so not subsampled).
    ds = bop.open_dataset(root)
    gts = bop.load_scene_gt(ds.scene_dir(1) / "scene_gt.json")
    results = bop.read_results(tmp_path / "out" / "results.csv")
    rows_by_obj: dict[int, list] = {}
    for r in results:
        rows_by_obj.setdefault((r.im_id, r.obj_id), []).append(r)
    errors: dict[int, list[float]] = {1: [], 2: []}
    for _scene, im, inst in OFFSETS:
        g = gts[im][inst]
        k = [i for i, h in enumerate(gts[im]) if h.obj_id == g.obj_id].index(inst)
        r = rows_by_obj[(im, g.obj_id)][k]
        pts = load_mesh(ds.model_path(g.obj_id)).vertices_m
        errors[g.obj_id].append(brute_adds(r.R, r.t_mm / 1000, g.R_m2c, g.t_m2c_m, pts))
    per_target = list(csv.DictReader(open(tmp_path / "out" / "per_target.csv")))
    assert len(per_target) == 5
    for row in per_target:
        dx, dyaw = OFFSETS[(int(row["scene_id"]), int(row["im_id"]), int(row["inst"]))]
        assert float(row["te_mm"]) == pytest.approx(1000 * dx, abs=1e-4)
        assert float(row["yaw_err_deg"]) == pytest.approx(math.degrees(dyaw), abs=1e-4)
        assert float(row["add_mm"]) >= float(row["adds_mm"]) - 1e-9
    for obj_id, e in errors.items():
        e = np.array(e)
        auc = 100 * np.mean(np.clip(1 - e / 0.1, 0, 1))  # closed form of the area, see pose_error.auc
        m = s["objects"][str(obj_id)]
        assert m["n"] == len(e)
        assert m["auc"] == pytest.approx(auc, abs=1e-6)
        assert m["adds_below_2cm_pct"] == pytest.approx(100 * np.mean(e < 0.02))
    all_e = np.concatenate([np.array(v) for v in errors.values()])
    assert s["pooled"]["auc"] == pytest.approx(100 * np.mean(np.clip(1 - all_e / 0.1, 0, 1)), abs=1e-6)
    # Thesis Table 4.1's "All Objects" is the mean over objects.
    assert s["all_objects"]["auc"] == pytest.approx((s["objects"]["1"]["auc"] + s["objects"]["2"]["auc"]) / 2)
    # Occlusion bins from visib_fract: 1 - 0.25 = 0.75 -> bin 7.
    assert s["occlusion"]["all"]["n"][7] == 1 and sum(s["occlusion"]["all"]["n"]) == 5
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert saved["objects"]["1"]["auc"] == pytest.approx(s["objects"]["1"]["auc"])
    assert "All Objects" in (tmp_path / "out" / "table.txt").read_text()


def test_results_are_bop_format_with_one_time_per_image(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    run_eval(root, tmp_path / "out", FakeEstimator())
    rows = bop.read_results(tmp_path / "out" / "results.csv")
    assert [(r.im_id, r.obj_id) for r in rows] == [(1, 1), (1, 1), (1, 2), (2, 2), (2, 1)]
    journal = [json.loads(line) for line in (tmp_path / "out" / "targets.jsonl").read_text().splitlines()]
    for im_id in (1, 2):
        times = {r.time_s for r in rows if r.im_id == im_id}
        assert len(times) == 1
        assert times.pop() == pytest.approx(sum(j["time_s"] for j in journal if j["im_id"] == im_id))


def test_interrupted_run_resumes_where_it_stopped(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    full = run_eval(root, tmp_path / "full", FakeEstimator())
    first = FakeEstimator(fail_after=2)
    with pytest.raises(KeyboardInterrupt):
        run_eval(root, tmp_path / "out", first)
    assert len(bop.read_results(tmp_path / "out" / "results.csv")) == 2  # saved as they finished
    second = FakeEstimator()
    resumed = run_eval(root, tmp_path / "out", second)
    assert len(second.calls) == 3 and not set(second.calls) & set(first.calls)
    assert resumed["objects"] == full["objects"] | {
        k: {**v, "mean_time_s": resumed["objects"][k]["mean_time_s"]} for k, v in full["objects"].items()
    }
    a = bop.read_results(tmp_path / "out" / "results.csv")
    b = bop.read_results(tmp_path / "full" / "results.csv")
    for ra, rb in zip(a, b, strict=True):
        np.testing.assert_array_equal(ra.R, rb.R)
        np.testing.assert_array_equal(ra.t_mm, rb.t_mm)
    # Without the journal, results.csv alone is enough to skip every target.
    (tmp_path / "out" / "targets.jsonl").unlink()
    third = FakeEstimator()
    again = run_eval(root, tmp_path / "out", third)
    assert third.calls == [] and again["pooled"]["auc"] == pytest.approx(full["pooled"]["auc"])


def test_changed_search_options_refuse_to_mix_unless_restarted(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    run_eval(root, tmp_path / "out", FakeEstimator(), options={"xy_step": 0.01})
    with pytest.raises(PerchError, match=r"other settings: --xy-step 0.01 then, 0.02 now; .*--restart") as e:
        run_eval(root, tmp_path / "out", FakeEstimator(), options={"xy_step": 0.02})
    assert len(str(e.value)) < 250  # the option that changed, briefly (it was ~970 characters)
    # The scores do not depend on the CPU threads: changing them resumes (nothing left to run).
    est = FakeEstimator()
    run_eval(root, tmp_path / "out", est, options={"xy_step": 0.01, "cpu_threads": 2})
    assert est.calls == []
    est = FakeEstimator()
    run_eval(root, tmp_path / "out", est, options={"xy_step": 0.02}, restart=True)
    assert len(est.calls) == 5


def test_object_and_image_selection(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    est = FakeEstimator()
    s = run_eval(root, tmp_path / "out", est, objects=[2], max_images=1)
    assert est.calls == [(1, 1, 3)] and list(s["objects"]) == ["2"] and s["skipped_no_model"] == {}


def test_plots_and_gallery_are_written(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    s = run_eval(root, tmp_path / "out", FakeEstimator(), plots=True, gallery=2)
    for name in ("adds_curve.png", "occlusion.png", "errors.png", "gallery.png"):
        assert (tmp_path / "out" / name).stat().st_size > 1000, name
        assert name in s["outputs"]


def test_no_occlusion_plot_without_scene_gt_info(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds", with_info=False)
    s = run_eval(root, tmp_path / "out", FakeEstimator(), plots=True, gallery=0)
    assert "occlusion" not in s and not (tmp_path / "out" / "occlusion.png").exists()


def test_command_line_wiring(tmp_path, monkeypatch, capsys):
    root = write_tiny_dataset(tmp_path / "ds")
    est = FakeEstimator()
    monkeypatch.setattr(command, "EngineEstimator", lambda *a, **k: est)
    p = argparse.ArgumentParser()
    command.add_arguments(p)
    args = p.parse_args(
        ["--dataset", str(root), "--out", str(tmp_path / "out"), "--objects", "1,2", "--no-plots", "--xy-step", "0.02"]
    )
    assert command.run(args) == 0
    out = capsys.readouterr().out
    assert "001 box" in out and "All Objects (mean)" in out and "Mean Runtime" in out
    assert len(est.calls) == 5
    config = json.loads((tmp_path / "out" / "eval_config.json").read_text())
    assert config["options"]["xy_step"] == 0.02 and "out" not in config["options"]


# ----------------------------------------------------------------------------- image labels

# Image 1 holds targets (1, 1, 0), (1, 1, 1), (1, 1, 3); image 2 holds (1, 2, 0), (1, 2, 1).
# Image 2's occlusion is not a string, so it is no label: the occlusion split covers image 1 only.
LABELS = {1: {"lighting": "normal", "occlusion": "high"}, 2: {"lighting": "harsh", "occlusion": 0.4}}


def write_labelled_dataset(root):
    """The tiny dataset, its scene_camera.json entries carrying the synthetic generator's labels."""
    root = write_tiny_dataset(root)
    path = root / "test" / "000001" / "scene_camera.json"
    cams = json.loads(path.read_text())
    for im_id, labels in LABELS.items():
        cams[str(im_id)].update(labels)
    path.write_text(json.dumps(cams))
    return root


def independent_adds_m(root, out) -> dict[tuple[int, int, int], float]:
    """ADD-S (m) per target from results.csv, by brute force (not the evaluator's KD-tree)."""
    ds = bop.open_dataset(root)
    gts = bop.load_scene_gt(ds.scene_dir(1) / "scene_gt.json")
    rows: dict[tuple[int, int], list] = {}
    for r in bop.read_results(out / "results.csv"):
        rows.setdefault((r.im_id, r.obj_id), []).append(r)
    errors = {}
    for scene, im, inst in OFFSETS:
        g = gts[im][inst]
        k = [i for i, h in enumerate(gts[im]) if h.obj_id == g.obj_id].index(inst)
        r = rows[(im, g.obj_id)][k]
        pts = load_mesh(ds.model_path(g.obj_id)).vertices_m
        errors[(scene, im, inst)] = brute_adds(r.R, r.t_mm / 1000, g.R_m2c, g.t_m2c_m, pts)
    return errors


def test_image_labels_are_string_values_of_known_keys():
    entry = {"cam_K": K, "lighting": "harsh", "occlusion": 3, "weather": "rain"}
    assert bop.image_labels(entry) == {"lighting": "harsh"}
    assert bop.image_labels({"cam_K": K}) == {}
    assert bop.IMAGE_LABEL_KEYS == ("lighting", "occlusion")


def test_metrics_by_image_label_agree_with_an_independent_computation(tmp_path):
    root = write_labelled_dataset(tmp_path / "ds")
    out = tmp_path / "out"
    s = run_eval(root, out, FakeEstimator(), plots=True, gallery=0)
    adds = independent_adds_m(root, out)
    groups = {
        "lighting": {"normal": [(1, 1, 0), (1, 1, 1), (1, 1, 3)], "harsh": [(1, 2, 0), (1, 2, 1)]},
        "occlusion": {"high": [(1, 1, 0), (1, 1, 1), (1, 1, 3)]},
    }
    by_label = s["by_label"]
    assert {k: list(v) for k, v in by_label.items()} == {k: list(v) for k, v in groups.items()}  # first-seen order
    for key, values in groups.items():
        for value, keys in values.items():
            m = by_label[key][value]
            e = np.array([adds[k] for k in keys])
            dx = np.array([OFFSETS[k][0] for k in keys])
            dyaw = np.array([OFFSETS[k][1] for k in keys])
            assert m["n"] == len(keys)
            assert m["adds_below_2cm_pct"] == pytest.approx(100 * np.mean(e < 0.02))
            assert m["auc"] == pytest.approx(100 * np.mean(np.clip(1 - e / 0.1, 0, 1)), abs=1e-6)
            # Translation and yaw errors are the fake estimator's known offsets.
            assert m["median_te_mm"] == pytest.approx(1000 * np.median(dx), abs=1e-4)
            assert m["mean_yaw_err_deg"] == pytest.approx(np.degrees(np.mean(dyaw)), abs=1e-4)
            assert m["mean_time_s"] is not None and m["mean_time_s"] >= 0
    # Guard against a vacuous check: the two lighting groups really differ.
    assert by_label["lighting"]["normal"]["median_te_mm"] == pytest.approx(15.0, abs=1e-4)
    assert by_label["lighting"]["harsh"]["median_te_mm"] == pytest.approx(62.0, abs=1e-4)

    saved = json.loads((out / "summary.json").read_text())
    assert saved["by_label"]["lighting"]["harsh"]["n"] == 2
    per_target = list(csv.DictReader(open(out / "per_target.csv")))
    for row in per_target:
        im = int(row["im_id"])
        assert row["lighting"] == LABELS[im]["lighting"]
        assert row["occlusion"] == ("high" if im == 1 else "")
    table = (out / "table.txt").read_text()
    for label in ("lighting = normal", "lighting = harsh", "occlusion = high"):
        assert label in table and label in s["table_text"]
    assert "occlusion = 0.4" not in table
    assert table.index("001 box") < table.index("lighting = normal")
    assert (out / "lighting.png").stat().st_size > 1000 and "lighting.png" in s["outputs"]


def test_occlusion_label_alone_gives_no_lighting_plot(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    path = root / "test" / "000001" / "scene_camera.json"
    cams = json.loads(path.read_text())
    for entry in cams.values():
        entry["occlusion"] = "low"
    path.write_text(json.dumps(cams))
    s = run_eval(root, tmp_path / "out", FakeEstimator(), plots=True, gallery=0)
    assert list(s["by_label"]) == ["occlusion"] and s["by_label"]["occlusion"]["low"]["n"] == 5
    assert s["by_label"]["occlusion"]["low"]["auc"] == pytest.approx(s["pooled"]["auc"])
    assert not (tmp_path / "out" / "lighting.png").exists()


def test_dataset_without_labels_has_no_label_breakdown(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    out = tmp_path / "out"
    s = run_eval(root, out, FakeEstimator(), plots=True, gallery=0)
    assert "by_label" not in s and "by_label" not in json.loads((out / "summary.json").read_text())
    assert not (out / "lighting.png").exists() and "lighting.png" not in s["outputs"]
    table = (out / "table.txt").read_text()
    assert "lighting =" not in table and "occlusion =" not in table
    per_target = list(csv.DictReader(open(out / "per_target.csv")))
    assert len(per_target) == 5 and all(r["lighting"] == "" and r["occlusion"] == "" for r in per_target)


# ----------------------------------------------------------------------------- journal reliability (issue 18)


def _journal(out) -> list[dict]:
    return [json.loads(x) for x in (out / "targets.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("row_in_results", [True, False], ids=["row kept", "row missing"])
def test_torn_last_journal_line_is_cut_before_appending(tmp_path, capsys, row_in_results):
    """A crash mid-write leaves the journal without its final newline. The fragment is cut off, so the next
    record starts on its own line; the target counts if results.csv has its row, else it runs again."""
    root = write_tiny_dataset(tmp_path / "ds")
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_eval(root, out, FakeEstimator(fail_after=2))
    lines = (out / "targets.jsonl").read_text().splitlines()
    torn = json.loads(lines[-1])
    (out / "targets.jsonl").write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])  # no newline
    if not row_in_results:
        rows = bop.read_results(out / "results.csv")
        kept = [r for r in rows if r.score != torn["score"]]  # the torn target's row (the last written)
        assert len(kept) == len(rows) - 1
        bop.write_results(out / "results.csv", kept)
    est = FakeEstimator()
    s = run_eval(root, out, est)
    err = capsys.readouterr().err
    assert "incomplete line" in err and "will run again" not in err
    key = (torn["scene_id"], torn["im_id"], torn["inst"])
    assert (key in est.calls) == (not row_in_results)
    journal = _journal(out)  # every line parses: nothing was appended onto the fragment
    assert len(journal) == 1 + len(est.calls) and s["n_evaluated"] == 5
    assert len(bop.read_results(out / "results.csv")) == 5
    # A second identical run changes nothing: the summary is stable.
    again = run_eval(root, out, FakeEstimator())
    assert again["pooled"]["auc"] == s["pooled"]["auc"] and _journal(out) == journal


def test_second_run_on_one_outdir_is_refused_and_nothing_is_corrupted(tmp_path):
    """While one eval holds OUTDIR, a second is refused at once naming the holder's pid; the first finishes."""
    import os
    import threading

    root = write_tiny_dataset(tmp_path / "ds")
    out = tmp_path / "out"
    inside, release = threading.Event(), threading.Event()

    class Slow(FakeEstimator):
        def __call__(self, *a):
            inside.set()
            assert release.wait(30)
            return super().__call__(*a)

    first = Slow()
    result: dict = {}
    t = threading.Thread(target=lambda: result.update(s=run_eval(root, out, first)))
    t.start()
    try:
        assert inside.wait(30)
        second = FakeEstimator()
        with pytest.raises(PerchError, match=rf"OUTDIR {out} is in use by another run \(pid {os.getpid()}\)"):
            run_eval(root, out, second)
        assert second.calls == []
    finally:
        release.set()
        t.join(60)
    assert result["s"]["n_evaluated"] == 5 and len(first.calls) == 5
    assert len(_journal(out)) == 5 and len(bop.read_results(out / "results.csv")) == 5
    assert not list(out.glob("*.tmp")) and not list(out.glob(".*.tmp"))
    run_eval(root, out, FakeEstimator())  # the lock went with the first run


def test_a_target_that_raises_is_recorded_and_the_run_finishes_the_others(tmp_path, capsys):
    root = write_tiny_dataset(tmp_path / "ds")
    out = tmp_path / "out"

    class Flaky(FakeEstimator):
        def __call__(self, target, *a):
            if target.key == (1, 1, 3):
                raise RuntimeError("CUDA error: an illegal memory access")
            return super().__call__(target, *a)

    est = Flaky()
    s = run_eval(root, out, est)
    assert s["n_failed"] == 1 and s["n_evaluated"] == 4 and len(est.calls) == 4
    assert s["failed"] == [{"key": [1, 1, 3], "reason": "RuntimeError: CUDA error: an illegal memory access"}]
    assert "(1, 1, 3) (obj 2) failed: RuntimeError" in capsys.readouterr().err
    assert len(bop.read_results(out / "results.csv")) == 4
    # A rerun tries the failed target again (the cause may be gone) and only it.
    again = FakeEstimator()
    s2 = run_eval(root, out, again)
    assert again.calls == [(1, 1, 3)] and s2["n_failed"] == 0 and s2["n_evaluated"] == 5


KILL_SCRIPT = """
import sys, time
sys.path.insert(0, {tests!r})
from test_evaluate import FakeEstimator, run_eval

class Slow(FakeEstimator):
    def __call__(self, *a):
        time.sleep(0.4)
        return super().__call__(*a)

run_eval({root!r}, {out!r}, Slow())
"""


def test_kill_9_mid_run_then_resume_gives_the_full_result(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    from _procs import sigkill_once_written

    root = write_tiny_dataset(tmp_path / "ds")
    out = tmp_path / "out"
    full = run_eval(root, tmp_path / "full", FakeEstimator())
    script = KILL_SCRIPT.format(tests=str(Path(__file__).parent), root=str(root), out=str(out))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sigkill_once_written(proc, out / "targets.jsonl", 2, 60)
    n_before = len(_journal(out))
    assert 2 <= n_before < 5
    est = FakeEstimator()
    resumed = run_eval(root, out, est)  # the dead process's lock is gone with it
    assert len(est.calls) == 5 - n_before
    assert resumed["pooled"]["auc"] == pytest.approx(full["pooled"]["auc"])
    assert len(_journal(out)) == 5 and not list(out.glob(".*.tmp"))


def test_resume_removes_the_temporaries_a_killed_run_left(tmp_path, capsys):
    """A run killed between atomic_write's mkstemp and its rename leaves `.NAME.*.tmp` in OUTDIR: the
    next run, holding the folder's lock, removes them and says so; it leaves other files alone."""
    root = write_tiny_dataset(tmp_path / "ds")
    out = tmp_path / "out"
    first = run_eval(root, out, FakeEstimator())
    stale = [out / ".results.csv.k3x9q1.tmp", out / ".targets.jsonl.a8b2c0.tmp"]
    stale.append(out / "heatmaps" / ".000001_000001_0.npz.p0q7zz.tmp")  # eval writes heat maps there
    stale[-1].parent.mkdir(exist_ok=True)
    for t in stale:
        t.write_text("half-writ")
    (out / "notes.tmp").write_text("the user's")
    capsys.readouterr()
    again = run_eval(root, out, FakeEstimator())
    assert not any(t.exists() for t in stale) and (out / "notes.tmp").exists()
    assert "removed 3 temporary file(s)" in capsys.readouterr().err
    assert again["pooled"]["auc"] == pytest.approx(first["pooled"]["auc"])


def test_rest_stable_reaches_the_estimator_and_is_recorded(tmp_path, monkeypatch, capsys):
    root = write_tiny_dataset(tmp_path / "ds")
    est, seen = FakeEstimator(), []

    def make(*a, **k):
        seen.append(a[4])  # the RestSpec (mode, roll step) after (paths, weights, device, config)
        return est

    monkeypatch.setattr(command, "EngineEstimator", make)
    p = argparse.ArgumentParser()
    command.add_arguments(p)
    base = ["--dataset", str(root), "--objects", "1", "--no-plots", "--xy-step", "0.02"]
    stable = ["--rest", "stable", "--roll-step", "45"]
    assert command.run(p.parse_args([*base, "--out", str(tmp_path / "a"), *stable])) == 0
    assert seen == [protocol.RestSpec("stable", 45.0)]
    options = json.loads((tmp_path / "a" / "eval_config.json").read_text())["options"]
    assert (options["rest"], options["roll_step"]) == ("stable", 45.0)
    # The thesis's protocol stays the default, recorded as before --rest existed (old OUTDIRs resume).
    assert command.run(p.parse_args([*base, "--out", str(tmp_path / "b")])) == 0
    assert seen[-1] == protocol.RestSpec("truth", 30.0)
    assert "rest" not in json.loads((tmp_path / "b" / "eval_config.json").read_text())["options"]


def test_separation_against_a_hand_computed_example():
    from perch_warp.eval.metrics import separation

    # Most confident first: None (no rival pose: above every number) right, 0.5 right, 0.4 wrong, 0.2 right,
    # 0.1 wrong. Top 50 % = ceil(2.5) = 3 answers, 2 right; top 80 % = 4, 3 right. ROC AUC: of the 3 x 2
    # (right, wrong) pairs, the right margin is larger in 5 (all but 0.2 < 0.4).
    s = separation([0.5, 0.4, None, 0.1, 0.2], [True, False, True, False, True])
    assert s["top50_accuracy_pct"] == pytest.approx(200 / 3) and s["top80_accuracy_pct"] == pytest.approx(75.0)
    assert s["roc_auc"] == pytest.approx(5 / 6) and s["accuracy_pct"] == pytest.approx(60.0)
    assert (s["n"], s["n_right"], s["n_wrong"]) == (5, 3, 2)
    # A tie between a right and a wrong answer counts half.
    assert separation([0.3, 0.3], [True, False])["roc_auc"] == pytest.approx(0.5)
    # All right: no ROC AUC.
    assert separation([0.3, 0.1], [True, True])["roc_auc"] is None


class ConfidentFakeEstimator(FakeEstimator):
    """The fake estimates with a confidence (larger for the nearer ones) and a small heat map each."""

    def __call__(self, target, image, camera, table, resting, space):
        from perch_warp.score_map import ScoreMap

        est = super().__call__(target, image, camera, table, resting, space)
        dx, _ = OFFSETS[target.key]
        est.details["confidence"] = {"margin": 0.1 - dx, "exact": True}
        xs, ys = np.array([-0.02, 0.0, 0.02]), np.array([-0.01, 0.01])
        best = np.array([[0.1, np.nan], [0.3, 0.2], [-np.inf, 0.1]])
        est.heatmap = ScoreMap(xs, ys, 0.02, best, np.where(np.isnan(best), 0.5, best), np.zeros((3, 2)), "pruned")
        return est


def test_confidence_columns_summary_and_worst_heat_maps(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    s = run_eval(root, tmp_path / "out", ConfidentFakeEstimator(), plots=True, gallery=2)
    rows = list(csv.DictReader(open(tmp_path / "out" / "per_target.csv")))
    margins = [float(r["confidence"]) for r in rows]
    right = [float(r["adds_mm"]) < 20.0 for r in rows]
    for r, m in zip(rows, margins, strict=True):
        dx, _ = OFFSETS[(int(r["scene_id"]), int(r["im_id"]), int(r["inst"]))]
        assert m == pytest.approx(0.1 - dx)
    from perch_warp.eval.metrics import separation

    assert s["confidence_separation"] == separation(margins, right)
    assert "Confidence (margin" in (tmp_path / "out" / "table.txt").read_text()
    assert len(list((tmp_path / "out" / "heatmaps").glob("*.npz"))) == 5
    assert "worst_heatmaps.png" in s["outputs"] and (tmp_path / "out" / "worst_heatmaps.png").stat().st_size > 0


def test_target_shares_average_to_the_pooled_figures():
    from perch_warp import pose_error
    from perch_warp.eval.metrics import target_shares

    rng = np.random.default_rng(3)
    adds = list(rng.uniform(0.0, 0.15, 40)) + [np.inf, None, np.nan]
    add = [None if e is None else e * 1.5 for e in adds]
    te = list(rng.uniform(0.0, 0.03, 43))
    s = target_shares(adds, add, te)
    assert s["auc"].mean() == pytest.approx(pose_error.auc(adds, 0.1), abs=1e-9)
    assert s["adds_below_2cm_pct"].mean() == pytest.approx(pose_error.accuracy_below(adds, 0.02))
    assert s["auc_add"].mean() == pytest.approx(pose_error.auc(add, 0.1), abs=1e-9)
    assert s["te_below_1cm_pct"].mean() == pytest.approx(pose_error.accuracy_below(te, 0.01))
    assert all(v[-3:].sum() == 0 for k, v in s.items() if k != "te_below_1cm_pct")  # failures share nothing


def test_mean_interval_against_hand_computed_cases():
    from perch_warp.eval.metrics import mean_interval

    assert mean_interval(np.full(7, 42.0)) == (42.0, 42.0)
    # Two targets, 0 and 100: a resample's mean is 0, 50 or 100 with chances 1/4, 1/2, 1/4.
    assert mean_interval(np.array([0.0, 100.0])) == (0.0, 100.0)
    # 50 right of 100: the mean's standard error is 5 points, so the interval is about 50 -/+ 9.8.
    lo, hi = mean_interval(np.repeat([0.0, 100.0], 50))
    assert lo == pytest.approx(40.2, abs=1.5) and hi == pytest.approx(59.8, abs=1.5)
    assert mean_interval(np.arange(9.0)) == mean_interval(np.arange(9.0))  # seeded


def test_summary_gives_intervals_around_the_pooled_figures(tmp_path):
    s = run_eval(write_tiny_dataset(tmp_path / "ds"), tmp_path / "out", FakeEstimator())
    for k in ("auc", "adds_below_2cm_pct", "auc_add", "te_below_1cm_pct"):
        lo, hi = s["pooled_ci95"][k]
        assert lo <= s["pooled"][k] + 1e-9 and s["pooled"][k] <= hi + 1e-9
    assert "95 % bootstrap intervals" in (tmp_path / "out" / "table.txt").read_text()


def test_the_estimators_candidate_count_wins_over_one_poses_grid(tmp_path):
    """Under several resting poses the search scores the grid once per pose: per_target.csv must carry
    the estimator's count, not the one pose's grid that the eval loop also knows."""

    class Counting(FakeEstimator):
        def __call__(self, target, image, camera, table, resting, space):
            est = super().__call__(target, image, camera, table, resting, space)
            if target.key == (1, 1, 0):
                est.details["n_candidates"] = 6 * len(space)
            return est

    root = write_tiny_dataset(tmp_path / "ds")
    run_eval(root, tmp_path / "out", Counting())
    rows = csv.DictReader(open(tmp_path / "out" / "per_target.csv"))
    counts = {(int(r["im_id"]), int(r["inst"])): int(r["n_candidates"]) for r in rows}
    # (1, 1, 0) and (1, 1, 1): the same object in the same image, so the same grid; only the first
    # estimator reported its own count.
    assert counts[(1, 0)] == 6 * counts[(1, 1)] > 0
