"""The heat map and the confidence: against the scores of the same poses (Engine.score), brute-force
references, and an ambiguous photo (two copies of the object) against an unambiguous one."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp import confidence as conf_mod
from perch_warp.confidence import DIFFERENT_XY_M, DIFFERENT_YAW_RAD, SYMMETRY_TOL_M, yaw_differs
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.pose_error import adi
from perch_warp.resting import stable_rests
from perch_warp.score_map import Knowledge, best_over_rest
from perch_warp.search_space import SearchSpace
from perch_warp.table import rot_z


@pytest.fixture(scope="module")
def scene():
    return demo_scene(seed=1)


def _space(scene, half=0.04, step=0.02, yaw_deg=45.0):
    gx, gy, _ = scene.truth_xy_yaw
    cx, cy = round(gx / step) * step, round(gy / step) * step
    return SearchSpace((cx - half, cx + half), (cy - half, cy + half), step, (0, 2 * math.pi), math.radians(yaw_deg))


def _all_scores(engine, scene, space):
    x, y, yaw = space.candidates()
    return engine.score(scene.image, scene.camera, scene.table, scene.resting, x, y, yaw)


def test_heat_map_is_the_best_score_over_yaw_of_the_same_poses(scene, random_weights):
    space = _space(scene)
    engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(search="exhaustive", refine=False))
    r = engine.estimate(scene.image, scene.camera, scene.table, scene.resting, space)
    xs, ys, yaws = space.axes()
    ref = _all_scores(engine, scene, space).reshape(len(xs), len(ys), len(yaws))
    assert np.array_equal(r.heatmap.best, ref.max(axis=2))
    assert np.array_equal(r.heatmap.best_yaw_rad, yaws[ref.argmax(axis=2)])
    assert np.array_equal(r.heatmap.xs_m, xs) and r.heatmap.n_unknown == 0 and r.heatmap.why_unknown == ""

    # Pruned (top 1): the cells it knows hold the same values; the others are NaN, and their bound holds.
    pruned = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(search="pruned", refine=False, top_k=1))
    p = pruned.estimate(scene.image, scene.camera, scene.table, scene.resting, space).heatmap
    known = ~np.isnan(p.best)
    assert np.array_equal(p.best[known], ref.max(axis=2)[known])
    assert np.all(ref.max(axis=2)[~known] <= p.upper[~known])
    assert p.n_unknown == 0 or "pruned" in p.why_unknown
    assert np.array_equal(r.heatmap.seen, r.heatmap.best) and np.array_equal(
        r.heatmap.seen_yaw_rad, r.heatmap.best_yaw_rad
    )


def test_seen_is_the_best_visited_pose_of_each_cell_where_best_is_unknown(scene, random_weights, tmp_path):
    space = _space(scene)
    full = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(search="exhaustive", refine=False))
    xs, ys, yaws = space.axes()
    ref = _all_scores(full, scene, space).reshape(len(xs), len(ys), len(yaws))
    cfg = EngineConfig(search="coarse-to-fine", refine=False, beam=2, coarse_xy_m=0.04, coarse_yaw_rad=math.radians(90))
    m = (
        Engine(scene.mesh, random_weights, DEVICE, cfg)
        .estimate(scene.image, scene.camera, scene.table, scene.resting, space)
        .heatmap
    )
    assert m.n_unknown > 0  # the pyramid leaves cells partly unvisited: their best is unknown
    visited = np.isfinite(m.seen)
    assert visited.sum() > len(xs) * len(ys) - m.n_unknown  # seen covers partly visited cells too
    i, j = np.nonzero(visited)
    k = np.rint((m.seen_yaw_rad[i, j] - yaws[0]) / (yaws[1] - yaws[0])).astype(int)
    assert np.array_equal(m.seen[i, j], ref[i, j, k])  # a visited pose's own score ...
    assert np.all(m.seen[i, j] <= ref.max(axis=2)[i, j])  # ... so at most the cell's best
    known = np.isfinite(m.best)
    assert np.array_equal(m.seen[known], m.best[known])
    assert np.all(np.isneginf(m.seen[~visited])) and np.all(np.isnan(m.seen_yaw_rad[~visited]))
    with open(tmp_path / "m.npz", "wb") as f:
        m.save(f)
    back = type(m).load(tmp_path / "m.npz")
    assert np.array_equal(back.seen, m.seen.astype(np.float32)) and np.array_equal(
        back.best, m.best.astype(np.float32), equal_nan=True
    )


def test_best_over_rest_takes_any_extra_axis_and_never_invents_values():
    # (x, y, rest, yaw) = (2, 1, 2, 2): cell 0 all known; cell 1 has an unknown whose bound beats the known.
    value = np.array([0.1, 0.5, 0.2, -np.inf, 0.3, np.nan, 0.1, 0.2])
    upper = np.array([0.1, 0.5, 0.2, -np.inf, 0.3, 0.9, 0.1, 0.2])
    best, up, arg, _ = best_over_rest(Knowledge(value, upper, (2, 1, 2, 2), "pruned"))
    assert best[0, 0] == 0.5 and arg[0, 0] == 1 and up[0, 0] == 0.5
    assert np.isnan(best[1, 0]) and up[1, 0] == 0.9
    # With the bound below the known best, the cell's best is known exactly.
    upper[5] = 0.25
    best, _, arg, _ = best_over_rest(Knowledge(value, upper, (2, 1, 2, 2), "pruned"))
    assert best[1, 0] == 0.3 and arg[1, 0] == 0


def _reference_margin(scene, space, scores, answer):
    """Brute force over the candidates, with ADD-S on every vertex for the yaw test."""
    V = scene.mesh.vertices_m
    R0 = scene.resting.R_rest
    a = [adi(rot_z(t) @ R0, np.zeros(3), R0, np.zeros(3), V) for t in (DIFFERENT_YAW_RAD, -DIFFERENT_YAW_RAD)]
    ref = max(SYMMETRY_TOL_M, *a)
    near, far = -np.inf, -np.inf
    for x, y, yaw, s in zip(*space.candidates(), scores, strict=True):
        d = abs((yaw - answer[2] + math.pi) % (2 * math.pi) - math.pi)
        turn = d > DIFFERENT_YAW_RAD + 1e-9 and adi(rot_z(yaw - answer[2]) @ R0, np.zeros(3), R0, np.zeros(3), V) > ref
        if math.hypot(x - answer[0], y - answer[1]) > DIFFERENT_XY_M + 1e-9 or turn:
            far = max(far, s)
        else:
            near = max(near, s)
    return near - far


def test_confidence_is_the_margin_to_the_best_clearly_different_pose(scene, random_weights):
    space = _space(scene)
    for search in ("exhaustive", "pruned"):
        engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(search=search, top_k=1, refine=False))
        r = engine.estimate(scene.image, scene.camera, scene.table, scene.resting, space)
        answer = (r.x_m, r.y_m, r.yaw_rad)
        want = _reference_margin(scene, space, _all_scores(engine, scene, space), answer)
        assert r.confidence.exact and r.confidence.margin == pytest.approx(want, abs=1e-12), search


def test_symmetries_about_the_table_normal_do_not_count_as_different_yaws():
    # A cylinder (body of revolution): no yaw counts. A 4 x 2 x 1 box: 180° does not, 90° does.
    t = np.linspace(0, 2 * math.pi, 720, endpoint=False)
    cyl = np.concatenate([np.stack([0.03 * np.cos(t), 0.03 * np.sin(t), np.full_like(t, z)], -1) for z in (0, 0.1)])
    offsets = np.radians([0.0, 10.0, 30.0, 90.0, 175.0, 180.0, 200.0])
    assert not yaw_differs(cyl, np.eye(3), offsets).any()
    g = np.linspace(-1, 1, 11)
    box = np.array([(x, y, z) for x in g for y in g for z in g]) * np.array([0.04, 0.02, 0.01])
    assert yaw_differs(box, np.eye(3), offsets).tolist() == [False, False, True, True, False, False, True]


@pytest.fixture(scope="module")
def caffe_engine(scene, caffe_weights):
    # The thesis's score: the margin's mechanics do not depend on the score, and this file's constructed
    # cases (two copies alike on the grid) were sized on its scale.
    return Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(search="exhaustive", refine=False, score="thesis"))


def test_two_copies_of_the_object_leave_no_margin(scene, caffe_engine):
    # One copy: the photographed object, rendered over itself; two: a second rendering 6 cm away (3 grid
    # steps, so that both copies sit alike on the grid). The second is as good an answer as the first.
    gx, gy, gyaw = scene.truth_xy_yaw
    step = 0.02
    cx, cy = round(gx / step) * step, round(gy / step) * step
    space = SearchSpace((cx - 0.02, cx + 0.08), (cy - 0.02, cy + 0.02), step, (0, 2 * math.pi), math.radians(30))
    from perch_warp.table import model_to_camera, pose_matrix

    def paste(img, x, y):
        R, t = model_to_camera(scene.table, scene.resting, x, y, gyaw)
        rgb, mask = caffe_engine.render(scene.camera, pose_matrix(R[0], t[0]))
        out = img.copy()
        out[mask] = (255 * rgb[mask]).round().astype(np.uint8)
        return out

    one = paste(scene.image, gx, gy)
    two = paste(one, gx + 0.06, gy)
    margins = []
    for img in (one, two):
        r = caffe_engine.estimate(img, scene.camera, scene.table, scene.resting, space)
        margins.append(r.confidence.margin)
    # (On this coarse grid the single object's margin is small too: its own pose lies between grid points.)
    assert margins[0] > 0 and abs(margins[1]) < 0.25 * margins[0], margins


def test_settle_scores_only_what_could_beat_the_known_best():
    k = Knowledge(np.array([0.5, np.nan, np.nan, 0.2]), np.array([0.5, 0.7, 0.4, 0.2]), (4,), "pruned")
    asked = []

    def score_fn(idx):
        asked.extend(idx.tolist())
        return np.full(len(idx), 0.45)

    assert conf_mod.settle(k, np.ones(4, bool), score_fn) == 1 and asked == [1]
    assert k.set_max(np.ones(4, bool))[:2] == (0.5, 0)


def test_heat_map_over_several_resting_poses_is_the_best_over_pose_and_yaw(scene, random_weights):
    rests = stable_rests(scene.mesh.vertices_m, scene.mesh.faces)[:3]
    space = _space(scene)
    xs, ys, yaws = space.axes()
    x, y, yaw = space.candidates()
    for search in ("exhaustive", "pruned"):
        engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(search=search, refine=False, top_k=2))
        hm = engine.estimate(scene.image, scene.camera, scene.table, rests, space).heatmap
        ref = np.stack(
            [engine.score(scene.image, scene.camera, scene.table, r.pose, x, y, yaw) for r in rests]
        ).reshape(len(rests), len(xs), len(ys), len(yaws))
        known = ~np.isnan(hm.best)
        assert np.array_equal(hm.best[known], ref.max(axis=(0, 3))[known])
        assert np.all(ref.max(axis=(0, 3))[~known] <= hm.upper[~known])
        if search == "exhaustive":
            assert known.all()
            # The yaw drawn is the yaw of the best (pose, yaw) of the cell.
            best = (
                ref.reshape(len(rests), len(xs), len(ys), len(yaws)).transpose(1, 2, 0, 3).reshape(len(xs), len(ys), -1)
            )
            assert np.array_equal(hm.best_yaw_rad, yaws[best.argmax(axis=2) % len(yaws)])


def test_heat_map_draws_the_best_seen_where_the_best_is_not_known(scene):
    """A coarse-to-fine map knows no cell's best, only what it scored: the picture shows those scores
    (faded, as lower bounds) and ranks its peaks over them, instead of a map that is grey throughout."""
    from perch_warp.heatmap import SEEN_FADE, UNKNOWN_GREY, _peaks, photo_layer, render_heatmap, shown_scores
    from perch_warp.score_map import ScoreMap

    xs, ys = np.arange(-0.04, 0.041, 0.01), np.arange(-0.03, 0.031, 0.01)
    rng = np.random.default_rng(3)
    seen = np.full((len(xs), len(ys)), -np.inf)
    visited = rng.random(seen.shape) < 0.5
    seen[visited] = rng.uniform(0.1, 0.6, visited.sum())
    seen[2, 3], seen[6, 1] = 0.9, 0.8  # two distinct places, the first the higher
    visited[2, 3] = visited[6, 1] = True
    best = np.full(seen.shape, np.nan)
    best[0, 0] = seen[0, 0] = 0.05  # one cell known exactly
    visited[0, 0] = True
    seen_yaw = np.where(visited, 0.5, np.nan)
    m = ScoreMap(xs, ys, 0.01, best, np.full(seen.shape, np.inf), np.where(np.isfinite(best), 0.5, np.nan),
                 "not visited by the coarse-to-fine search", seen, seen_yaw)  # fmt: skip

    values, seen_only = shown_scores(m)
    assert np.array_equal(seen_only, visited & np.isnan(best))
    assert values[0, 0] == 0.05 and np.array_equal(values[seen_only], seen[seen_only])
    assert np.all(np.isnan(values[~visited]))
    peaks = _peaks(m, values)
    assert len(m.peaks(5, 1)) == 1  # the known bests alone: one low cell
    assert [(round(p[0], 3), round(p[1], 3), p[3]) for p in peaks[:2]] == [
        (round(xs[2], 3), round(ys[3], 3), 0.9),
        (round(xs[6], 3), round(ys[1], 3), 0.8),
    ]

    # Over the photo: the seen cell of 0.9 is coloured (faded), a cell nothing scored is grey.
    import matplotlib as mpl

    from perch_warp.heatmap import _norm, cell_quads

    cmap, norm = mpl.colormaps["viridis"], _norm(values)
    photo = np.zeros((scene.camera.height, scene.camera.width, 3), dtype=np.uint8)
    layer = photo_layer(photo, scene.camera, scene.table, m, cmap, norm).astype(float)
    uv, _ = cell_quads(m, scene.camera, scene.table)

    def centre(i, j):
        u, v = np.rint(uv[i, j].mean(axis=0)).astype(int)
        return layer[v, u]

    want = ((1 - SEEN_FADE) * np.asarray(cmap(norm(0.9))[:3]) + SEEN_FADE * np.asarray(UNKNOWN_GREY)) * 255 * 0.55
    assert np.allclose(centre(2, 3), want, atol=2.0)
    grey = np.argwhere(~visited)[0]
    assert np.allclose(centre(*grey), np.asarray(UNKNOWN_GREY) * 255 * 0.55, atol=2.0)
    assert render_heatmap(photo, scene.camera, scene.table, m, (xs[2], ys[3], 0.5), "t")[:4] == b"\x89PNG"
