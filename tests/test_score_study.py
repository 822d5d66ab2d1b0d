"""tools/score_study.py from-run: each target's pool is the best cells its search scored (the heat map's
`seen`), best first, and its truth the ground truth on the table; heat maps without `seen` are refused."""

import json

import numpy as np
from _tools import load_tool
from test_bop import write_tiny_dataset
from test_evaluate import FakeEstimator, run_eval

from perch_warp import bop
from perch_warp.demo import demo_scene
from perch_warp.score_map import ScoreMap
from perch_warp.table import decompose_on_table

XS, YS = np.array([-0.02, 0.0, 0.02]), np.array([-0.01, 0.01])
SEEN = np.array([[0.1, 0.7], [0.3, -np.inf], [0.5, 0.2]])
SEEN_YAW = np.where(np.isfinite(SEEN), np.arange(6).reshape(3, 2) * 0.5, np.nan)


class SeenEstimator(FakeEstimator):
    """The fake estimates, each with a heat map whose best is unknown everywhere but whose `seen` is SEEN."""

    def __init__(self, with_seen: bool = True):
        super().__init__()
        self.with_seen = with_seen

    def __call__(self, target, image, camera, table, resting, space):
        est = super().__call__(target, image, camera, table, resting, space)
        nan = np.full(SEEN.shape, np.nan)
        seen = (SEEN, SEEN_YAW) if self.with_seen else (None, None)
        est.heatmap = ScoreMap(XS, YS, 0.02, nan, np.full(SEEN.shape, np.inf), nan, "not visited", *seen)
        return est


def test_from_run_pools_the_best_seen_cells_and_the_truth(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    run_eval(root, tmp_path / "run", SeenEstimator())
    with (tmp_path / "run" / "targets.jsonl").open("a") as f:  # a failed target's record: no heat map, no pool
        f.write(json.dumps({"scene_id": 1, "im_id": 9, "inst": 0, "obj_id": 1, "failed": "boom"}) + "\n")
    tool = load_tool("score_study")
    assert tool.main(["from-run", str(tmp_path / "run"), "--out", str(tmp_path / "pool.json"), "--pool", "3"]) == 0
    pool = json.loads((tmp_path / "pool.json").read_text())
    ds = bop.open_dataset(root, "test", None)
    truth = {tuple(t.key): (im, t) for im in bop.select_targets(ds).images for t in im.targets}
    assert sorted(tuple(r["key"]) for r in pool["targets"]) == sorted(truth)
    tables = bop.TableCache("auto")
    for r in pool["targets"]:
        # the three best finite cells of SEEN: (0, 1) 0.7, (2, 0) 0.5, (1, 0) 0.3, at their seen yaw
        assert r["pool"] == [[-0.02, 0.01, 0.5], [0.02, -0.01, 2.0], [0.0, -0.01, 1.0]]
        assert np.array_equal(np.float32(r["pool_scores"]), np.float32([0.7, 0.5, 0.3]))  # stored as float32
        im, t = truth[tuple(r["key"])]
        _, x, y, yaw = decompose_on_table(tables.get(im)[0], t.R_gt, t.t_gt_m)
        assert np.allclose(r["gt"], [x, y, yaw])


def test_from_run_refuses_heat_maps_without_seen(tmp_path, capsys):
    root = write_tiny_dataset(tmp_path / "ds")
    run_eval(root, tmp_path / "run", SeenEstimator(with_seen=False))
    tool = load_tool("score_study")
    assert tool.main(["from-run", str(tmp_path / "run"), "--out", str(tmp_path / "pool.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert "before heat maps kept 'seen'" in err and "\n" not in err and not (tmp_path / "pool.json").exists()


def test_from_run_on_a_folder_that_is_not_a_run(tmp_path, capsys):
    tool = load_tool("score_study")
    assert tool.main(["from-run", str(tmp_path), "--out", str(tmp_path / "pool.json")]) == 1
    assert "eval_config.json: not found" in capsys.readouterr().err


def test_rescore_engines_use_the_alpha_asked_for(random_weights):
    """`rescore --alpha A`: both the grid's engine and the refining one (which drops the grid's shift)
    reduce with the top-A fraction, so a study of A compares what a search at A would score."""
    study = load_tool("score_study")
    grid, fine = study._engines(demo_scene(seed=1).mesh, random_weights, "centred", 0.35)
    assert grid.config.alpha == fine.config.alpha == 0.35
    assert grid.terms.shift == 1 and fine.terms.shift == 0


def _pool_file(path, dataset, rows, score):
    meta = {"dataset": dataset, "models": None, "weights": "caffe", "score": score, "targets": rows}
    path.write_text(json.dumps(meta))
    return path


def test_merge_interleaves_pools_by_rank_drops_repeats_and_keeps_shared_targets(tmp_path):
    row = {"key": [1, 1, 0], "obj_id": 3, "rgb": "x.png", "gt": [0, 0, 0]}
    a = [{**row, "pool": [[1, 0, 0], [2, 0, 0], [3, 0, 0]]}, {**row, "key": [1, 2, 0], "pool": [[9, 0, 0]]}]
    b = [{**row, "pool": [[5, 0, 0], [1, 0, 0], [6, 0, 0], [7, 0, 0]]}]
    tool = load_tool("score_study")
    pa, pb = _pool_file(tmp_path / "a.json", "DS", a, "thesis"), _pool_file(tmp_path / "b.json", "DS", b, "centred")
    assert tool.main(["merge", str(pa), str(pb), "--out", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert [r["key"] for r in m["targets"]] == [[1, 1, 0]]  # only the target both pools hold
    # rank 1 of each, rank 2 of each ([1, 0, 0] again: dropped), rank 3 of each, rank 4 of b
    assert m["targets"][0]["pool"] == [[1, 0, 0], [5, 0, 0], [2, 0, 0], [3, 0, 0], [6, 0, 0], [7, 0, 0]]
    assert m["score"] == ["thesis", "centred"] and m["targets"][0]["gt"] == [0, 0, 0]


def test_merge_refuses_pools_of_different_datasets(tmp_path, capsys):
    tool = load_tool("score_study")
    pa = _pool_file(tmp_path / "a.json", "DS1", [], "thesis")
    pb = _pool_file(tmp_path / "b.json", "DS2", [], "thesis")
    assert tool.main(["merge", str(pa), str(pb), "--out", str(tmp_path / "m.json")]) == 1
    assert "different datasets" in capsys.readouterr().err and not (tmp_path / "m.json").exists()


def test_merge_names_a_from_run_pools_score_and_refuses_a_missing_pool(tmp_path, capsys):
    row = {"key": [1, 1, 0], "obj_id": 3, "rgb": "x.png", "gt": [0, 0, 0], "pool": [[1, 0, 0]], "pool_scores": [0.5]}
    pa = _pool_file(tmp_path / "a.json", "DS", [row], "thesis")
    run = {"dataset": "DS", "models": None, "weights": "caffe", "run_options": {"score": "centred"}, "targets": [row]}
    (tmp_path / "b.json").write_text(json.dumps(run))
    tool = load_tool("score_study")
    assert tool.main(["merge", str(pa), str(tmp_path / "b.json"), "--out", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["score"] == ["thesis", "centred"] and "pool_scores" not in m["targets"][0]
    capsys.readouterr()
    missing = tmp_path / "nope.json"
    assert tool.main(["merge", str(pa), str(missing), "--out", str(tmp_path / "m2.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert f"{missing}: not found" in err and "\n" not in err and not (tmp_path / "m2.json").exists()
