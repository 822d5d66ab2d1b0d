"""tools/peaks_replay.py: a K = 1 eval run replayed with K peaks answers as `eval --refine-peaks K` does.

The reference is eval itself: the demo scene as a BOP dataset, searched over a small region by eval
with --refine-peaks 1 and with --refine-peaks 3; replaying the first with K = 3 must give the second's
answers bit for bit, and the first's own (K = 1) answers."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from _tools import load_tool

from perch_warp.cli import main
from perch_warp.demo import demo_scene, write_scene
from perch_warp.eval.plots import heatmap_path
from perch_warp.score_map import ScoreMap


@pytest.fixture(scope="module")
def tool():
    return load_tool("peaks_replay")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """(dataset, the K = 1 run, the K = 3 run): eval on the demo scene, coarse-to-fine on a small region."""
    d = tmp_path_factory.mktemp("replay")
    sc = demo_scene(seed=4)  # a scene where refining 3 peaks changes the answer (checked below)
    write_scene(sc, d / "scene")
    ds = d / "ds"
    scene_dir = ds / "test" / "000001"
    shutil.copytree(d / "scene" / "rgb", scene_dir / "rgb")
    for name in ("scene_camera.json", "scene_gt.json"):
        shutil.copy(d / "scene" / name, scene_dir)
    shutil.copytree(d / "scene" / "models", ds / "models")
    gx, gy, _ = sc.truth_xy_yaw
    x, y = round(gx, 2), round(gy, 2)
    base = [
        "eval", "--dataset", str(ds), "--device", "cpu", "--search", "coarse-to-fine", "--beam", "16",
        "--xy-step", "0.04", "--yaw-step", "60", "--coarse-xy", "0.08", "--coarse-yaw", "120",
        "--refine-xy", "0.01", "--refine-yaw", "10", "--no-plots",
        "--x-range", f"{x - 0.2}", f"{x + 0.06}", "--y-range", f"{y - 0.06}", f"{y + 0.18}",
    ]  # fmt: skip
    assert main([*base, "--out", str(d / "k1")]) == 0
    assert main([*base, "--out", str(d / "k3"), "--refine-peaks", "3"]) == 0
    return ds, d / "k1", d / "k3"


def _journal(out: Path) -> dict:
    return {
        tuple(j[k] for k in ("scene_id", "im_id", "inst")): j for j in map(json.loads, (out / "targets.jsonl").open())
    }


def test_replay_gives_evals_own_k_peaks_answer_bit_for_bit(tool, runs, tmp_path):
    _, k1, k3 = runs
    assert tool.main([str(k1), "--out", str(tmp_path / "r3"), "--refine-peaks", "3", "--device", "cpu"]) == 0
    rows = [json.loads(x) for x in (tmp_path / "r3" / "replay.jsonl").open()]
    want = _journal(k3)
    assert len(rows) == len(want) == 1
    for r in rows:
        w = want[tuple(r["key"])]
        assert not r["same_as_run"]  # the second or third peak wins: the new answer's path is the one tested
        assert r["answer"]["score"] == w["score"]  # bit for bit
        assert [p["score"] for p in r["peaks"]] == [p["score"] for p in w["details"]["refine"]["peaks"]]
        assert r["check"]["refined_score"] == _journal(k1)[tuple(r["key"])]["score"]
    with (tmp_path / "r3" / "per_target.csv").open() as f, (k3 / "per_target.csv").open() as g:
        mine, theirs = list(csv.DictReader(f)), list(csv.DictReader(g))
    assert [float(a["adds_mm"]) for a in mine] == pytest.approx([float(b["adds_mm"]) for b in theirs], abs=1e-6)


def test_replay_with_one_peak_gives_the_runs_own_answers(tool, runs, tmp_path):
    _, k1, _ = runs
    assert tool.main([str(k1), "--out", str(tmp_path / "r1"), "--refine-peaks", "1", "--device", "cpu"]) == 0
    rows = [json.loads(x) for x in (tmp_path / "r1" / "replay.jsonl").open()]
    assert rows and all(r["same_as_run"] for r in rows)
    with (tmp_path / "r1" / "per_target.csv").open() as f, (k1 / "per_target.csv").open() as g:
        assert [r["adds_mm"] for r in csv.DictReader(f)] == [r["adds_mm"] for r in csv.DictReader(g)]


def test_a_heat_map_that_disagrees_with_the_scores_is_a_one_line_error(tool, runs, tmp_path, capsys):
    _, k1, _ = runs
    run = tmp_path / "run"
    shutil.copytree(k1, run)
    key = next(iter(_journal(k1)))
    path = heatmap_path(run, key)
    smap = ScoreMap.load(path)
    seen = smap.seen.copy()
    i, j = np.unravel_index(np.nanargmax(np.where(np.isfinite(seen), seen, -np.inf)), seen.shape)
    seen[i, j] += 0.01  # the best location's score no longer what the run scored
    smap.seen = seen
    smap.save(path)
    assert tool.main([str(run), "--out", str(tmp_path / "bad"), "--device", "cpu"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "scores" in err and "in the run's heat map" in err
    assert not (tmp_path / "bad" / "per_target.csv").exists()


def test_a_pruned_run_is_refused(tool, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "eval_config.json").write_text(json.dumps({"dataset": "d", "options": {"search": "pruned"}}))
    assert tool.main([str(run), "--out", str(tmp_path / "o")]) == 1
    assert "only coarse-to-fine and exhaustive" in capsys.readouterr().err


def test_a_folder_without_eval_config_is_a_one_line_error(tool, tmp_path, capsys):
    assert tool.main([str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip()
    assert "eval_config.json not found" in err and "\n" not in err


def test_a_journal_without_the_refinement_record_is_a_one_line_error(tool, runs, tmp_path, capsys):
    _, k1, _ = runs
    run = tmp_path / "run"
    shutil.copytree(k1, run)
    lines = [json.loads(x) for x in (run / "targets.jsonl").open()]
    for j in lines:
        j["details"].pop("refine")
    (run / "targets.jsonl").write_text("".join(json.dumps(j) + "\n" for j in lines))
    (run / "results.csv").unlink()  # the journal is then the only record
    assert tool.main([str(run), "--out", str(tmp_path / "o"), "--device", "cpu"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "has no refinement record in the run's journal" in err


def test_shards_side_by_side_give_the_whole_runs_rows(tool, runs, tmp_path):
    _, k1, _ = runs
    out = tmp_path / "sharded"
    for i in range(2):  # one target: shard 0 takes it, shard 1 has none
        assert (
            tool.main([str(k1), "--out", str(out), "--refine-peaks", "1", "--device", "cpu", "--shard", f"{i}/2"]) == 0
        )
    assert tool.main([str(k1), "--out", str(out), "--limit", "0", "--device", "cpu"]) == 0
    assert len([json.loads(x) for x in (out / "replay.jsonl").open()]) == len(_journal(k1))
    with (out / "per_target.csv").open() as f, (k1 / "per_target.csv").open() as g:
        assert [r["adds_mm"] for r in csv.DictReader(f)] == [r["adds_mm"] for r in csv.DictReader(g)]


@pytest.mark.parametrize("spec", ["2/2", "1", "a/b", "0/0"])
def test_a_bad_shard_is_a_one_line_error(tool, spec, tmp_path):
    with pytest.raises(SystemExit, match="--shard"):
        tool.shard_of(spec)


def test_a_line_cut_short_is_skipped_and_said(tool, tmp_path, capsys):
    path = tmp_path / "replay.jsonl"
    path.write_text('{"key": [1, 1, 0]}\n{"key": [1, 1\n{"key": [1, 2, 0]}\n')
    assert [r["key"] for r in tool.read_journal(path)] == [[1, 1, 0], [1, 2, 0]]
    assert "line 2 is cut short" in capsys.readouterr().err
