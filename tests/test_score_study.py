"""tools/score_study.py from-run: each target's pool is the best cells its search scored (the heat map's
`seen`), best first, and its truth the ground truth on the table; heat maps without `seen` are refused.
values and reductions: the stored feature-point values reduce to the engine's scores, and each reduction
is its definition."""

import json
import math

import numpy as np
import pytest
from _tools import load_tool
from test_bop import write_tiny_dataset
from test_evaluate import FakeEstimator, run_eval

from perch_warp import bop, pose_error
from perch_warp.demo import demo_scene
from perch_warp.image import load_rgb
from perch_warp.score import top_alpha_mean
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


def test_reductions_are_their_definitions_and_never_fall_when_a_value_rises():
    """`reductions`' family against direct NumPy definitions on random values, and each non-decreasing in
    every value (what keeps a silhouette bound of the same reduction admissible)."""
    study = load_tool("score_study")
    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 40, 333):
        v = rng.normal(0.3, 0.3, n)
        scores = {k: s[0] for k, s in study.reduce_values(v, np.array([n]), list(study.REDUCTIONS)).items()}
        s = np.sort(v)[::-1]
        for a in (0.25, 0.35, 0.5, 0.7, 1.0):
            assert scores[f"top{a}"] == pytest.approx(top_alpha_mean(v, np.array([0, n]), a)[0][0], abs=1e-12)
        for t in (0.0, 0.1, 0.2, 0.3):
            assert scores[f"floor{t}"] == pytest.approx(np.mean([max(x, t) for x in v]), abs=1e-12)
        for p in (0.1, 0.2, 0.3, 0.5):
            brute = max(s[:k].mean() * (k / n) ** p for k in {max(1, math.ceil(a * n - 1e-9)) for a in
                        np.linspace(0.2, 1.0, 17)})  # fmt: skip
            assert scores[f"adaptive{p}"] == pytest.approx(brute, abs=1e-12)
        k = max(1, math.ceil(0.5 * n - 1e-9))
        for k0 in (16, 64):
            assert scores[f"shrink{k0}"] == pytest.approx(s[:k].sum() / (k + k0), abs=1e-12)
        for _ in range(5):
            w = v.copy()
            w[rng.integers(n)] += rng.uniform(0, 0.5)
            raised = study.reduce_values(w, np.array([n]), list(study.REDUCTIONS))
            assert all(raised[name][0] >= scores[name] - 1e-12 for name in scores)


def test_values_of_a_target_are_the_scores_the_refining_engine_gives(tmp_path, random_weights):
    """`values`' per-target record: the pool, each far peak's cell and the truth's cell (kinds 0, 1, 2), the
    truth's ADD-S 0 at its own pose, and values whose top-0.5 mean is the engine's score below the grid."""
    from perch_warp.engine import Engine, EngineConfig
    from perch_warp.mesh import load_mesh

    study = load_tool("score_study")
    root = write_tiny_dataset(tmp_path / "ds")
    sel = bop.select_targets(bop.open_dataset(root, "test", None))
    im, tg = sel.images[0], sel.images[0].targets[0]
    tables = bop.TableCache("auto")
    table = tables.get(im)[0]
    resting, x, y, yaw = decompose_on_table(table, tg.R_gt, tg.t_gt_m)
    row = {
        "key": list(tg.key),
        "gt": [x, y, yaw],
        "pool": [[x + 0.05, y, yaw], [x, y - 0.05, 1.0], [x + 0.004, y, yaw]],
    }
    mesh = load_mesh(sel.model_paths[tg.obj_id])
    engine = Engine(mesh, random_weights, "cpu", EngineConfig(score="centred", alpha=0.5))
    points = pose_error.subsample_points(np.asarray(mesh.vertices_m))
    data = study.values_target(engine, points, im, tg, row, tables, peaks=3)
    # the two pool poses farther than 2 cm from the truth are far peaks, each with a 125-pose cell
    assert np.array_equal(np.bincount(data["kind"]), [3, 250, 125])
    truth = np.flatnonzero(data["kind"] == 2)[62]  # the cell's centre: the truth itself
    assert np.allclose(data["poses"][truth], [x, y, yaw]) and data["adds_m"][truth] < 1e-6
    assert data["adds_m"][0] > 0.02 and data["adds_m"][2] < 0.01 and data["image_scale"] == 1.0
    fine = engine.scoring(load_rgb(im.rgb), im.camera, table, resting).refining()
    want = fine.score(tuple(data["poses"].T))
    got = study.reduce_values(data["values"], data["lens"], ["top0.5"])["top0.5"]
    assert np.isfinite(want).sum() > 300
    assert np.array_equal(np.isinf(got), np.isinf(want))
    assert np.allclose(got[np.isfinite(want)], want[np.isfinite(want)], rtol=0, atol=1e-6)


def _write_values(folder, key, vals, adds, poses=None):
    """A made-up `values` file: one pose per array of values (the last one the truth's cell)."""
    study = load_tool("score_study")
    folder.mkdir(parents=True, exist_ok=True)
    n = len(vals)
    np.savez(
        folder / study.values_file(key),
        key=np.array(key),
        obj_id=np.int64(1),
        visib_fract=np.float64(0.35),
        poses=np.zeros((n, 3)) if poses is None else poses,
        kind=np.array([0] * (n - 1) + [2], np.int8),
        adds_m=np.array(adds),
        lens=np.array([len(v) for v in vals]),
        values=np.concatenate(vals).astype(np.float32),
    )


def test_reductions_pair_each_pick_with_the_base(tmp_path, capsys):
    """`reductions` on two made-up targets, each a truth 35 % visible (those points match well, the rest
    not at all) against a look-alike matching middling everywhere: the top-0.5 mean (the base) picks the
    truth in both, the plain mean (floor0.0) the look-alike in both, and the losses are named by target."""
    study = load_tool("score_study")
    rng = np.random.default_rng(0)
    look_alike = np.full(100, 0.45) + rng.normal(0, 0.01, 100)
    truth = np.concatenate([np.full(35, 0.9), np.full(65, 0.0)])  # 35 % visible: 0.63 at top-0.5, 0.315 as a plain mean
    for key, vals, adds in (((1, 1, 0), [look_alike, truth], [0.2, 0.0]), ((1, 2, 0), [truth, look_alike], [0.0, 0.2])):
        _write_values(tmp_path, key, vals, adds)
    assert study.main(["reductions", str(tmp_path)]) == 0
    out = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[2:]}
    assert "+[] -[]" in out["top0.5"] and "100.00" in out["top0.5"]
    assert "-[(1, 1, 0), (1, 2, 0)]" in out["floor0.0"]  # the mean of all: 0.315 < 0.45, the look-alike wins both
    assert study.main(["reductions", str(tmp_path / "none")]) == 1
    assert study.main(["reductions", str(tmp_path), "--base", "top0.4"]) == 1
    err = capsys.readouterr().err
    assert "no values_*.npz" in err and "--base top0.4: not a reduction" in err


def test_blend_weighs_the_second_scales_top_half_means_and_pairs_with_the_first(tmp_path, capsys):
    """`blend` on one made-up target: at the first scale a look-alike's values (0.6) beat the truth's (0.5),
    at the second the truth's (0.9) beat the look-alike's (0.1). Weight 0 is the first scale alone (the
    look-alike); (1 - w) a + w b with w = 0.1 still picks it (0.55 > 0.54), w = 0.25 the truth (0.6 > 0.475).
    A third pose has no points at the first scale: it never wins, not even at w = 1 (0 x -inf is nan)."""
    study = load_tool("score_study")
    key = (1, 3, 0)
    _write_values(tmp_path / "full", key, [np.full(40, 0.6), np.zeros(0), np.full(40, 0.5)], [0.2, 0.3, 0.0])
    _write_values(tmp_path / "half", key, [np.full(10, 0.1), np.full(10, 1.0), np.full(10, 0.9)], [0.2, 0.3, 0.0])
    args = ["blend", str(tmp_path / "full"), str(tmp_path / "half"), "--weights", "0.1", "0.25", "1"]
    assert study.main(args) == 0
    out = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[2:]}
    assert "+[] -[]" in out["w0"] and " 0.00 " in out["w0"]  # the look-alike, 20 cm away: AUC 0
    assert "+[] -[]" in out["w0.1"]
    assert "+[(1, 3, 0)] -[]" in out["w0.25"] and "100.00" in out["w0.25"]
    assert "+[(1, 3, 0)] -[]" in out["w1"]
    # the second folder must hold the same target at the same poses
    _write_values(tmp_path / "moved", key, [np.full(10, 0.1)] * 3, [0.2, 0.3, 0.0], poses=np.ones((3, 3)))
    assert study.main(["blend", str(tmp_path / "full"), str(tmp_path / "moved")]) == 1
    assert study.main(["blend", str(tmp_path / "full"), str(tmp_path / "none")]) == 1
    err = capsys.readouterr().err.splitlines()
    assert "other poses than" in err[0] and "missing (both folders need the same targets)" in err[1]


@pytest.mark.parametrize("command", ["values", "rescore"])
def test_a_missing_pool_is_named_in_one_line(tmp_path, capsys, command):
    study = load_tool("score_study")
    extra = ["--out", str(tmp_path / "v")] if command == "values" else ["--score", "thesis"]
    assert study.main([command, str(tmp_path / "nope.json"), *extra]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "nope.json: not found" in err and err.count("\n") == 1
    assert not (tmp_path / "v").exists()


def test_hidden_top_mean_is_its_definition_and_never_falls_when_a_visible_value_rises():
    """occlusion's reduction: the best k visible values over k, k = ceil(0.5 max(V, ceil(beta N)))."""
    study = load_tool("score_study")
    v = np.array([0.9, 0.8, 0.1, 0.5, 0.7, 0.2, 0.0, 0.3])
    hidden = np.array([False, True, False, True, False, True, True, True])  # visible: 0.9, 0.1, 0.7
    assert study.hidden_top_mean(v, hidden, 0.0) == pytest.approx((0.9 + 0.7) / 2)  # k = ceil(1.5) = 2
    assert study.hidden_top_mean(v, hidden, 0.5) == pytest.approx((0.9 + 0.7) / 2)  # max(3, 4) -> k = 2
    assert study.hidden_top_mean(v, hidden, 1.0) == pytest.approx((0.9 + 0.7 + 0.1) / 4)  # k = 4 > V: missing = 0
    assert study.hidden_top_mean(v, np.zeros(8, bool), 0.25) == pytest.approx((0.9 + 0.8 + 0.7 + 0.5) / 4)
    assert study.hidden_top_mean(v, np.ones(8, bool), 0.25) == -math.inf
    rng = np.random.default_rng(1)
    for _ in range(50):
        n = int(rng.integers(1, 40))
        w, hid, beta = rng.uniform(-0.2, 1, n), rng.random(n) < 0.6, float(rng.choice([0, 0.25, 0.5, 1]))
        before = study.hidden_top_mean(w, hid, beta)
        w[rng.integers(n)] += rng.uniform(0, 0.5)
        assert study.hidden_top_mean(w, hid, beta) >= before - 1e-12


def test_hidden_points_are_under_a_nearer_occluders_silhouette_only():
    study = load_tool("score_study")
    mask = np.zeros((48, 64), bool)
    mask[10:20, 30:40] = True
    uv = np.array([[35, 15], [5, 5], [39, 19], [40, 15], [-3, 15], [35, 60]])  # in, out, corner in, edge out, off
    assert study.hidden_points(uv, 1.0, [(mask, 0.8)]).tolist() == [True, False, True, False, False, False]
    assert not study.hidden_points(uv, 1.0, [(mask, 1.2)]).any()  # the occluder stands behind the pose
    assert not study.hidden_points(uv, 1.0, []).any()


def test_occlusion_drops_what_another_targets_answer_hides(tmp_path, capsys):
    """`occlusion` on a made-up target of the tiny dataset (image 2's box, (1, 2, 1)), hidden behind the
    run's answer for the cylinder (1, 2, 0): its truth shows 20 of 100 points (0.9 each), the other 80 lie
    under the cylinder's rendered silhouette (0.0); a look-alike shows 40 points of 0.45 in the open; a
    pose farther back shows 5 points (1.0) beside the cylinder and hides 95. The top-0.5 mean of all
    points takes the look-alike (0.36 < 0.45); dropping the hidden points with beta 0 takes the pose
    hiding behind the cylinder (its 5 points: 1.0); beta 0.25 counts at least 13 points (the hider:
    5/13 = 0.38) and takes the truth (0.9); beta 1 counts 50 again (the look-alike)."""
    from perch_warp.eval.plots import silhouette
    from perch_warp.mesh import load_mesh

    study = load_tool("score_study")
    root = write_tiny_dataset(tmp_path / "ds")
    run_eval(root, tmp_path / "run", FakeEstimator())
    sel = bop.select_targets(bop.open_dataset(root, "test", None))
    im = next(i for i in sel.images if i.im_id == 2)
    (_, obj, R, t), *_ = study.run_answers(tmp_path / "run", sel)[(1, 2)]
    mesh = load_mesh(sel.model_paths[obj])
    under = np.argwhere(silhouette(im.camera, np.asarray(mesh.vertices_m), np.asarray(mesh.faces), R, t))[:, ::-1]
    assert obj == 2 and len(under) > 20
    d = float(np.linalg.norm(t))
    free = np.array([[2, 2], [3, 40], [60, 2]])  # corners the cylinder does not reach
    rng = np.random.default_rng(0)
    pick = lambda px, n: px[rng.integers(len(px), size=n)]  # noqa: E731
    poses = [  # (values, pixels, distance from the camera, ADD-S)
        (np.full(40, 0.45), pick(free, 40), d + 0.2, 0.2),
        (np.r_[np.full(5, 1.0), np.zeros(95)], np.r_[pick(free, 5), pick(under, 95)], d + 0.1, 0.3),
        (np.r_[np.full(20, 0.9), np.zeros(80)], np.r_[pick(free, 20), pick(under, 80)], d + 0.05, 0.0),
    ]
    folder = tmp_path / "values"
    folder.mkdir()
    np.savez(
        folder / study.values_file((1, 2, 1)),
        key=np.array([1, 2, 1]),
        obj_id=np.int64(1),
        visib_fract=np.float64(0.2),
        poses=np.zeros((3, 3)),
        kind=np.array([0, 0, 2], np.int8),
        adds_m=np.array([p[3] for p in poses]),
        lens=np.array([len(p[0]) for p in poses]),
        values=np.concatenate([p[0] for p in poses]).astype(np.float32),
        uv=np.concatenate([p[1] for p in poses]).astype(np.int16),
        dist_m=np.array([p[2] for p in poses]),
        run=np.str_(str(tmp_path / "run")),
    )
    assert study.main(["occlusion", str(folder), "--verbose"]) == 0
    lines = capsys.readouterr().out.splitlines()
    out = {line.split()[0]: line for line in lines[2:-1]}
    assert "top0.5 20.0 cm" in lines[-1] and "hidden0 30.0 cm" in lines[-1] and "hidden0.25 0.0 cm" in lines[-1]
    assert "hidden1 20.0 cm" in lines[-1]
    assert "+[] -[]" in out["top0.5"] and " 0.00 " in out["top0.5"]  # the look-alike, 20 cm off
    assert "+[] -[]" in out["hidden0"]  # the hider, 30 cm off
    assert "+[(1, 2, 1)] -[]" in out["hidden0.25"] and "100.00" in out["hidden0.25"]
    assert "+[] -[]" in out["hidden1"]
    # the picture of the two picks: one 400 x 300 tile per target named; a key without values is named
    pic = tmp_path / "pic.jpg"
    assert study.main(["occlusion", str(folder), "--betas", "0.25", "--draw", str(pic), "--draw-keys", "1/2/1"]) == 0
    from PIL import Image

    with Image.open(pic) as im_pic:
        assert im_pic.size == (400, 300) and im_pic.format == "JPEG"
    assert study.main(["occlusion", str(folder), "--draw", str(tmp_path / "x.jpg"), "--draw-keys", "1/1/0"]) == 1
    assert study.main(["occlusion", str(folder), "--draw", str(tmp_path / "x.jpg")]) == 1
    assert study.main(["occlusion", str(folder), "--draw", str(tmp_path / "x.jpg"), "--draw-keys", "1-2-1"]) == 1
    err = capsys.readouterr().err
    assert "values_1_1_0.npz: missing" in err and "--draw FILE and --draw-keys KEY ... go together" in err
    assert "--draw-keys '1-2-1': name a target as scene/image/instance, e.g. 1/12/0" in err
    assert not (tmp_path / "x.jpg").exists()
    # the truth's own silhouettes hide nothing of this made-up target's points the same way, but they run
    assert study.main(["occlusion", str(folder), "--occluders", "truth", "--betas", "0.25"]) == 0
    capsys.readouterr()
    _write_values(tmp_path / "plain", (1, 2, 1), [np.full(4, 0.5)], [0.0])  # values without --pixels
    assert study.main(["occlusion", str(tmp_path / "plain")]) == 1
    assert "write the values with `values --pixels`" in capsys.readouterr().err


@pytest.mark.parametrize("flag", ["--pixels", "--around"])
def test_point_pixels_need_a_pool_that_names_its_run(tmp_path, capsys, flag):
    """The hidden points come from the pool's run (its answers, its dataset): a collected pool has none."""
    study = load_tool("score_study")
    root = write_tiny_dataset(tmp_path / "ds")
    pool = _pool_file(tmp_path / "pool.json", str(root), [], "thesis")
    assert study.main(["values", str(pool), "--out", str(tmp_path / "v"), flag]) == 1
    assert "no run recorded (--pixels and --around need a pool made by from-run)" in capsys.readouterr().err
