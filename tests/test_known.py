"""Known scores (perch_warp.search.known) and the test that decides which candidates an occluder map cannot
touch (perch_warp.hidden): a second search that takes the first search's scores where nothing can be
hidden gives what a second search scoring every candidate gives, bit for bit, on Warp's CPU device."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.hidden import BoxMinima, hidden_points
from perch_warp.search.known import KnownScores
from perch_warp.table import model_to_camera, pose_matrix


def _least_by_loop(v: np.ndarray, box) -> float:
    x, y, w, h = (int(a) for a in box)
    xs, ys, xe, ye = max(x, 0), max(y, 0), min(x + w, v.shape[1]), min(y + h, v.shape[0])
    return float(v[ys:ye, xs:xe].min()) if xe > xs and ye > ys else np.inf


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (6, 1), (13, 17), (64, 64), (47, 80)])
def test_box_minima_equal_a_loop_over_each_box(shape):
    rng = np.random.default_rng(sum(shape))
    v = rng.random(shape).astype(np.float32)
    v[rng.random(shape) < 0.6] = np.inf
    v[shape[0] // 2, shape[1] // 2] = 0.5
    boxes = np.stack(
        [
            rng.integers(-6, shape[1] + 3, 400),
            rng.integers(-6, shape[0] + 3, 400),
            rng.integers(0, 50, 400),
            rng.integers(0, 50, 400),
        ],
        axis=1,
    )
    got = BoxMinima(v).least(boxes)
    want = np.array([_least_by_loop(v, b) for b in boxes], dtype=np.float32)
    assert np.array_equal(got, want)
    assert np.isfinite(want).sum() > 50 and np.isinf(want).sum() > 20  # both kinds of box occur


def test_untouched_is_the_kernels_test_over_the_box():
    rng = np.random.default_rng(5)
    near = np.full((30, 40), np.inf, dtype=np.float32)
    near[5:15, 10:22] = 0.8
    near[20:26, 30:38] = 1.1
    hidden = hidden_points(near, 0.25, 2, DEVICE)
    boxes = np.stack(
        [rng.integers(-5, 40, 500), rng.integers(-5, 30, 500), rng.integers(0, 12, 500), rng.integers(0, 12, 500)],
        axis=1,
    )
    dist = rng.uniform(0.6, 1.3, 500)
    want = np.array([_least_by_loop(near, b) >= np.float32(d) for b, d in zip(boxes, dist, strict=True)])
    t_m = np.zeros((len(dist), 3))
    t_m[:, 2] = dist  # straight ahead: the translation's norm is the distance
    got = hidden.untouched(boxes, t_m)
    assert np.array_equal(got, want) and 50 < got.sum() < 450


@pytest.fixture(scope="module")
def scene_and_occluder(random_weights):
    """The demo scene, its engine (the default score), and an occluder: the demo box itself at the pose
    nearest the camera among a few around the truth (as tests/test_hidden.py places it)."""
    scene = demo_scene(seed=1, yaw_step_deg=30.0, half_range_m=0.08)
    engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig())
    gx, gy, _ = scene.truth_xy_yaw
    rng = np.random.default_rng(1)
    x, y, yaw = gx + rng.uniform(-0.08, 0.08, 30), gy + rng.uniform(-0.08, 0.08, 30), rng.uniform(0, 6.28, 30)
    R, t = model_to_camera(scene.table, scene.resting, x, y, yaw)
    near = int(np.argmin(np.linalg.norm(t, axis=1)))
    return scene, engine, pose_matrix(R[near], t[near])


def _same_result(a, b) -> None:
    def poses(r):
        return [(c.x_m, c.y_m, c.yaw_rad, c.score) for c in r.top_k]

    assert poses(a) == poses(b)
    assert a.n_scored == b.n_scored and a.info.evaluated == b.info.evaluated
    assert np.array_equal(a.heatmap.best, b.heatmap.best, equal_nan=True)


@pytest.mark.parametrize("search", ["pruned", "coarse-to-fine", "exhaustive"])
def test_second_search_with_known_scores_equals_scoring_every_candidate(scene_and_occluder, search):
    scene, engine, T_occ = scene_and_occluder
    engine = Engine(scene.mesh, engine.weights, DEVICE, dataclasses.replace(engine.config, search=search))
    args = (scene.image, scene.camera, scene.table, scene.resting, scene.space)
    photo = engine.photo(scene.image, scene.camera)
    known = KnownScores(photo)
    first = engine.estimate(*args, photo=photo, known=known)
    plain_first = engine.estimate(*args, photo=photo)
    _same_result(first, plain_first)  # keeping scores changes nothing
    assert first.info.extra["known"]["scores_kept"] > 0
    hidden = engine.hidden_by(scene.camera, [(engine, T_occ)])
    again = engine.estimate(*args, photo=photo, hidden=hidden)  # every candidate scored
    reused = engine.estimate(*args, photo=photo, hidden=hidden, known=known)
    _same_result(reused, again)
    n = reused.info.extra["known"]
    # Some candidates are taken (those the occluder cannot reach), some scored anew (those behind it).
    assert n["scores_reused"] > 0 and 0 < reused.info.rays < again.info.rays
    if search != "exhaustive":  # the searches that bound candidates take the known bounds too
        assert n["bounds_reused"] > 0


def test_taken_scores_are_what_scoring_gives_and_touched_ones_are_not_taken(scene_and_occluder):
    """Direct: every score the service takes equals the score computed afresh with the map; candidates
    the map can touch are always scored (their plain scores differ where a point is hidden)."""
    scene, engine, T_occ = scene_and_occluder
    photo = engine.photo(scene.image, scene.camera)
    x, y, yaw = scene.space.candidates()
    plain = engine.scoring(scene.image, scene.camera, scene.table, scene.resting)
    plain = dataclasses.replace(plain, photo=photo)
    known = KnownScores(photo)
    kept = dataclasses.replace(plain, known=known).score((x, y, yaw))
    assert np.array_equal(kept, plain.score((x, y, yaw))) and known.counts["scores_kept"] > 0
    hidden = engine.hidden_by(scene.camera, [(engine, T_occ)])
    fresh = dataclasses.replace(plain, hidden=hidden).score((x, y, yaw))
    taken = dataclasses.replace(plain, hidden=hidden, known=known).score((x, y, yaw))
    assert np.array_equal(taken, fresh)
    assert 0 < known.counts["scores_reused"] < np.isfinite(fresh).sum()
    bounds = dataclasses.replace(plain, known=known).bound((x, y, yaw))  # kept as scores are
    assert np.array_equal(bounds, plain.bound((x, y, yaw))) and known.counts["bounds_kept"] > 0
    fresh_bounds = dataclasses.replace(plain, hidden=hidden).bound((x, y, yaw))
    assert np.array_equal(dataclasses.replace(plain, hidden=hidden, known=known).bound((x, y, yaw)), fresh_bounds)
    assert 0 < known.counts["bounds_reused"] < np.isfinite(fresh_bounds).sum()
    assert np.any(fresh_bounds != bounds)
    # Where the scores differ from the plain ones, a point was hidden: never one the service took.
    c = plain.candidates(x, y, yaw)
    touched = ~hidden.untouched(c.gboxes, c.tr)
    assert np.all(touched[fresh != kept]) and (fresh != kept).sum() > 0


def test_known_scores_of_another_photo_are_refused(scene_and_occluder):
    scene, engine, _ = scene_and_occluder
    photo = engine.photo(scene.image, scene.camera)
    other = engine.photo(scene.image[::-1].copy(), scene.camera)
    args = (scene.image, scene.camera, scene.table, scene.resting, scene.space)
    with pytest.raises(PerchError, match="another photo"):
        engine.estimate(*args, photo=other, known=KnownScores(photo))
    with pytest.raises(PerchError, match="photo="):
        engine.estimate(*args, known=KnownScores(photo))
