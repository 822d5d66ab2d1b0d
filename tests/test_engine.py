"""End to end: scenes photographed from known poses (lighting, shadows, noise) are recovered."""

import json
import math

import numpy as np
import pytest
from _device import DEVICE

import perch_warp.search.scoring as scoring
from perch_warp.camera import camera_from_entry
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.image import load_rgb
from perch_warp.mesh import load_mesh
from perch_warp.pose_error import adi
from perch_warp.score_terms import parse_score
from perch_warp.search.base import top_indices
from perch_warp.search_space import SearchSpace
from perch_warp.table import Table, decompose_on_table, model_to_camera


def _space_around(x, y, half=0.04, step=0.01, yaw_step_deg=30.0):
    """A square containing (x, y) but centred a little off it, on the step grid."""
    cx, cy = round(x / step) * step + step, round(y / step) * step - step
    return SearchSpace(
        (cx - half, cx + half), (cy - half, cy + half), step, (0, 2 * math.pi), math.radians(yaw_step_deg)
    )


@pytest.fixture(scope="module")
def scene():
    return demo_scene(seed=1)


def _yaw_err_deg(a, b):
    return abs(math.degrees((a - b + math.pi) % (2 * math.pi) - math.pi))


def test_recovers_known_pose_within_one_grid_step(scene, caffe_weights):
    gx, gy, gyaw = scene.truth_xy_yaw
    space = _space_around(gx, gy)
    cfg = EngineConfig(search="exhaustive", refine=False)
    r = Engine(scene.mesh, caffe_weights, DEVICE, cfg).estimate(
        scene.image, scene.camera, scene.table, scene.resting, space
    )
    assert abs(r.x_m - gx) <= 0.01 + 1e-9 and abs(r.y_m - gy) <= 0.01 + 1e-9
    assert _yaw_err_deg(r.yaw_rad, gyaw) <= 30.0
    assert r.n_scored == r.n_candidates == len(space)
    # The returned transform is the candidate's pose on the table.
    R, t = model_to_camera(scene.table, scene.resting, r.x_m, r.y_m, r.yaw_rad)
    assert np.allclose(r.T_m2c[:3, :3], R[0]) and np.allclose(r.T_m2c[:3, 3], t[0])
    assert [c.score for c in r.top_k] == sorted((c.score for c in r.top_k), reverse=True)


def test_same_answer_twice_and_for_any_batch_size(scene, random_weights):
    gx, gy, _ = scene.truth_xy_yaw
    space = _space_around(gx, gy, half=0.02, yaw_step_deg=45.0)
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    a = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(refine=False)).estimate(*args)
    b = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(refine=False)).estimate(*args)
    c = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(batch_pixels=5000, refine=False)).estimate(*args)
    assert c.info.batches > a.info.batches
    for other in (b, c):
        assert [(k.x_m, k.y_m, k.yaw_rad) for k in other.top_k] == [(k.x_m, k.y_m, k.yaw_rad) for k in a.top_k]
        assert np.allclose([k.score for k in other.top_k], [k.score for k in a.top_k], rtol=0, atol=1e-6)


def test_cpu_threads_give_the_same_scores_as_one(scene, random_weights):
    gx, gy, _ = scene.truth_xy_yaw
    space = _space_around(gx, gy, half=0.02, yaw_step_deg=45.0)
    args = (scene.image, scene.camera, scene.table, scene.resting, space)

    def run(threads):
        config = EngineConfig(
            batch_pixels=5000, top_k=len(space), cpu_threads=threads, search="exhaustive", refine=False
        )
        return Engine(scene.mesh, random_weights, DEVICE, config).estimate(*args)

    one, two = run(1), run(2)
    assert one.info.batches > 2 and (two.info.batches, two.info.rays) == (
        one.info.batches,
        one.info.rays,
    )
    # Every candidate, bit for bit and in the same order.
    assert [(k.x_m, k.y_m, k.yaw_rad, k.score) for k in two.top_k] == [
        (k.x_m, k.y_m, k.yaw_rad, k.score) for k in one.top_k
    ]


def test_real_frame_potted_meat_can(shared, caffe_weights):
    """YCB-Video frame: the potted meat can (obj 9, standing on the sugar box) within 2 cm ADD-S."""
    d = shared / "data" / "ycbv" / "test" / "000002"
    image = load_rgb(d / "rgb" / "000001.png")
    entry = json.loads((d / "scene_camera.json").read_text())["1"]
    camera = camera_from_entry(entry, image.shape[1], image.shape[0])
    table = Table.from_entry(entry)
    gt = next(g for g in json.loads((d / "scene_gt.json").read_text())["1"] if g["obj_id"] == 9)
    R_gt, t_gt = np.reshape(gt["cam_R_m2c"], (3, 3)), np.asarray(gt["cam_t_m2c"]) / 1000
    resting, gx, gy, _ = decompose_on_table(table, R_gt, t_gt)
    mesh = load_mesh(shared / "data" / "ycbv" / "models" / "obj_000009.obj")
    space = _space_around(gx, gy, half=0.03, yaw_step_deg=15.0)
    r = Engine(mesh, caffe_weights, DEVICE, EngineConfig(refine=False)).estimate(image, camera, table, resting, space)
    assert adi(r.T_m2c[:3, :3], r.T_m2c[:3, 3], R_gt, t_gt, mesh.vertices_m) < 0.02


def test_coarse_to_fine_scores_a_subset_and_matches_exhaustive_here(scene, caffe_weights):
    gx, gy, _ = scene.truth_xy_yaw
    space = _space_around(gx, gy, half=0.06, yaw_step_deg=15.0)
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    ex = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(search="exhaustive", refine=False)).estimate(*args)
    cfg = EngineConfig(search="coarse-to-fine", coarse_xy_m=0.04, coarse_yaw_rad=math.radians(45), beam=4, refine=False)
    c2f = Engine(scene.mesh, caffe_weights, DEVICE, cfg).estimate(*args)
    assert c2f.info.evaluated < len(space) / 3
    assert (c2f.x_m, c2f.y_m, c2f.yaw_rad) == (ex.x_m, ex.y_m, ex.yaw_rad)
    assert c2f.score == pytest.approx(ex.score, abs=1e-6)


def test_top_indices_are_a_stable_sorts_first_k():
    rng = np.random.default_rng(0)
    scores = rng.integers(0, 6, 300).astype(float)  # many ties
    scores[rng.choice(300, 40, replace=False)] = -np.inf
    for k in (1, 5, 17, 300, 400):
        np.testing.assert_array_equal(top_indices(scores, k), np.argsort(-scores, kind="stable")[:k])
    few = np.array([-np.inf, 2.0, -np.inf])
    np.testing.assert_array_equal(top_indices(few, 5), [1, 0, 2])


@pytest.mark.parametrize("search", ["exhaustive", "pruned", "coarse-to-fine"])
def test_candidates_are_set_up_a_chunk_at_a_time(scene, random_weights, monkeypatch, search):
    """No step sets up more than SETUP_CHUNK candidates' poses and boxes at once, and the answer
    does not depend on the chunk size."""
    space = _space_around(*scene.truth_xy_yaw[:2], half=0.03, yaw_step_deg=45.0)  # 7 x 7 x 8 = 392
    cfg = EngineConfig(search=search, coarse_xy_m=0.02, coarse_yaw_rad=math.radians(90), beam=4, top_k=5, refine=False)
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    whole = Engine(scene.mesh, random_weights, DEVICE, cfg).estimate(*args)

    sizes = []
    setup = scoring.ScoringService.candidates

    def spy(self, x, y, yaw):
        sizes.append(len(x))
        return setup(self, x, y, yaw)

    monkeypatch.setattr(scoring, "SETUP_CHUNK", 23)
    monkeypatch.setattr(scoring.ScoringService, "candidates", spy)
    chunked = Engine(scene.mesh, random_weights, DEVICE, cfg).estimate(*args)
    assert sizes and max(sizes) <= 23
    if search != "coarse-to-fine":  # every candidate set up, in chunks
        assert sum(sizes) >= len(space)
    assert [(c.x_m, c.y_m, c.yaw_rad) for c in chunked.top_k] == [(c.x_m, c.y_m, c.yaw_rad) for c in whole.top_k]
    np.testing.assert_allclose([c.score for c in chunked.top_k], [c.score for c in whole.top_k], rtol=0, atol=1e-6)
    # The pruned search's rounds also stop at a chunk, so it may score fewer; what it bounds is the same.
    for key in ("bounded",) if search == "pruned" else ("evaluated",):
        assert chunked.info.to_dict()[key] == whole.info.to_dict()[key]


def test_half_scale_search_finds_the_pose_too(scene, caffe_weights):
    gx, gy, gyaw = scene.truth_xy_yaw
    space = _space_around(gx, gy)
    cfg = EngineConfig(image_scale=0.5, refine=False)
    r = Engine(scene.mesh, caffe_weights, DEVICE, cfg).estimate(
        scene.image, scene.camera, scene.table, scene.resting, space
    )
    assert abs(r.x_m - gx) <= 0.01 + 1e-9 and abs(r.y_m - gy) <= 0.01 + 1e-9
    assert _yaw_err_deg(r.yaw_rad, gyaw) <= 30.0
    # The pose is still expressed for the full-size camera (metres, model -> camera).
    R, t = model_to_camera(scene.table, scene.resting, r.x_m, r.y_m, r.yaw_rad)
    assert np.allclose(r.T_m2c[:3, 3], t[0])


def test_both_conv_forms_give_the_same_scores(scene, caffe_weights):
    """Kernel #2's conv1 in the Warp kernel or through torch's conv2d: every candidate's score equal up
    to float rounding, and the torch threads as they were once the search is over."""
    import torch

    from perch_warp.errors import PerchError

    gx, gy, _ = scene.truth_xy_yaw
    space = _space_around(gx, gy, half=0.02, yaw_step_deg=45.0)
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    threads = torch.get_num_threads()
    runs = {}
    for conv in ("warp", "torch"):
        # grid-tolerant: the default score's centre term runs in the torch form alone.
        config = EngineConfig(
            conv=conv, top_k=len(space), search="exhaustive", refine=False, batch_pixels=20000, score="grid-tolerant"
        )
        runs[conv] = Engine(scene.mesh, caffe_weights, DEVICE, config).estimate(*args)
        assert (runs[conv].info.conv, runs[conv].info.conv_option) == (conv, conv)
    assert torch.get_num_threads() == threads
    by_pose = {conv: {(k.x_m, k.y_m, k.yaw_rad): k.score for k in r.top_k} for conv, r in runs.items()}
    assert by_pose["warp"].keys() == by_pose["torch"].keys() and len(by_pose["warp"]) > 20
    diff = [abs(by_pose["warp"][p] - by_pose["torch"][p]) for p in by_pose["warp"] if np.isfinite(by_pose["warp"][p])]
    assert max(diff) < 1e-5
    assert runs["warp"].best.score == pytest.approx(runs["torch"].best.score, abs=1e-5)
    with pytest.raises(PerchError, match="--conv"):
        EngineConfig(conv="cudnn")


def test_centre_term_needs_the_torch_form_and_raw_conv1(scene, random_weights):
    """The centre term keeps each candidate's features to average them: kernel #2's torch form only."""
    with pytest.raises(PerchError, match="use --conv torch"):
        Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="centre=0.5", conv="warp"))
    with pytest.raises(PerchError, match="drop --relu"):
        Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="centre=0.5", conv="torch", relu=True))
    Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="centre=0.5", conv="torch"))
    # The default score has the term, so the error names a score without it as well.
    assert parse_score(EngineConfig().score)[1].centre > 0.0
    with pytest.raises(PerchError, match="drop --relu, or use a score without them .e.g. --score grid-tolerant"):
        Engine(scene.mesh, random_weights, DEVICE, EngineConfig(relu=True))
    one = "uses centre=0.5 .* which needs raw conv1: drop --relu, or use a score without it "
    with pytest.raises(PerchError, match=one):
        Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="centre=0.5", relu=True))
    Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="grid-tolerant", relu=True))


def test_auto_conv_keeps_features_for_the_centre_term(monkeypatch):
    """conv "auto" is torch on the CPU and warp on a GPU, except that a centred score needs the torch form there
    too (it keeps each candidate's features); the CLI's line says why."""
    import types

    from perch_warp import score
    from perch_warp.report import conv_line

    assert score.auto_conv("cpu") == score.auto_conv("cpu", 0.5) == "torch"
    monkeypatch.setattr(score.wp, "get_device", lambda device: types.SimpleNamespace(is_cpu=False))
    assert score.auto_conv("cuda:0") == "warp"
    assert score.auto_conv("cuda:0", 0.5) == "torch"
    info = types.SimpleNamespace(conv="torch", conv_option="auto", score="centre=0.5")
    result = types.SimpleNamespace(device="cuda:0", info=info)
    assert "centre term needs it" in conv_line(result)
    result.info.conv_option = "torch"
    assert "auto" not in conv_line(result)


def test_rectified_term_with_relu_is_refused(scene, random_weights):
    """The rectified term blends raw and rectified conv1; with --relu there are no raw features to blend."""
    with pytest.raises(PerchError, match="drop --relu"):
        Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="rectified=0.5", relu=True))
