"""Points other objects hide (perch_warp.hidden, kernels/hidden.py, the reduction in kernels/reduce.py),
against NumPy references and an independent path (full-image renderings looked up at each point's pixel)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import warp as wp
from _device import DEVICE
from perch_warp.kernels.features import NOT_ON_MASK
from perch_warp.kernels.hidden import HIDDEN

from perch_warp.bound import BOUND_SLACK
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.hidden import HiddenPoints, hidden_points, hide, occluder_map
from perch_warp.render import point_layout
from perch_warp.score import hidden_count, top_alpha_mean, top_alpha_mean_device
from perch_warp.table import model_to_camera, pose_matrix

H = HIDDEN


def _device_scores(values, offsets, alpha, beta, shrink=0.0):
    v = wp.array(np.asarray(values, np.float32), dtype=float, device=DEVICE)
    o = wp.array(np.asarray(offsets, np.int32), dtype=wp.int32, device=DEVICE)
    s, n = top_alpha_mean_device(v, o, alpha, shrink, beta=beta)
    return s.numpy(), n.numpy()


def test_reduction_counts_k_from_the_visible_points_or_beta_n_hand_numbers():
    # 8 points on the mask, 4 hidden, one off the mask; alpha 0.5.
    vals = [0.9, 0.8, H, H, 0.1, NOT_ON_MASK, 0.2, H, H]
    for beta, want in [(0.25, (0.9 + 0.8) / 2), (0.5, (0.9 + 0.8) / 2), (1.0, (0.9 + 0.8 + 0.2 + 0.1) / 4)]:
        got, n = top_alpha_mean(np.array(vals), np.array([0, 9]), 0.5, beta=beta)
        dev, dn = _device_scores(vals, [0, 9], 0.5, beta)
        assert got[0] == pytest.approx(want) and dev[0] == pytest.approx(want, abs=1e-6)
        assert n[0] == dn[0] == 8
    # One visible of 8: beta 0.25 counts 2 (k = 1); beta 0.5 counts 4 (k = 2: the missing point is 0).
    one = [0.9, H, H, H, H, H, H, H]
    assert _device_scores(one, [0, 8], 0.5, 0.25)[0][0] == pytest.approx(0.9)
    assert _device_scores(one, [0, 8], 0.5, 0.5)[0][0] == pytest.approx(0.45)
    # Every point hidden: -inf, as a pose that shows none.
    assert _device_scores([H, H], [0, 2], 0.5, 0.25)[0][0] == -np.inf
    assert hidden_count(0.25, 3, 3) == 3 and hidden_count(0.25, 1, 8) == 2 and hidden_count(0.25, 5, 8) == 5


@pytest.mark.parametrize("beta", [0.0, 0.25, 0.6])
def test_device_reduction_with_hidden_points_equals_the_numpy_reference(beta):
    rng = np.random.default_rng(3)
    lens = rng.integers(0, 60, 300)
    offsets = np.concatenate([[0], np.cumsum(lens)])
    vals = rng.normal(0.3, 0.4, offsets[-1]).astype(np.float32)
    vals[rng.random(len(vals)) < 0.15] = NOT_ON_MASK
    hidden_share = rng.random(len(lens))  # each candidate hidden to its own degree, some wholly
    for c in range(len(lens)):
        seg = slice(offsets[c], offsets[c + 1])
        hid = rng.random(lens[c]) < hidden_share[c]
        vals[seg][hid & (vals[seg] != NOT_ON_MASK)] = HIDDEN
    vals[: offsets[5]] = np.round(vals[: offsets[5]], 1)  # ties
    for alpha, shrink in [(0.5, 0.0), (0.3, 4.0)]:
        ref, n = top_alpha_mean(vals, offsets, alpha, shrink, beta)
        got, dn = _device_scores(vals, offsets, alpha, beta, shrink)
        assert np.array_equal(n, dn)
        assert np.array_equal(np.isfinite(ref), np.isfinite(got))
        ok = np.isfinite(ref)
        assert ok.sum() > 200 and np.allclose(got[ok], ref[ok], rtol=0, atol=1e-6)
    # Without hidden points beta plays no part: the plain top-α mean, bit for bit on the device.
    plain = np.where(vals == HIDDEN, np.float32(0.05), vals)
    assert np.array_equal(_device_scores(plain, offsets, 0.5, beta)[0], _device_scores(plain, offsets, 0.5, 0.0)[0])


def test_occluder_map_keeps_the_nearest_silhouette_at_each_cells_pixel():
    ks, stride, rows, cols = 3, 2, 4, 5  # cell (gx, gy) at pixel (1 + 2 gx, 1 + 2 gy)
    a = np.zeros((10, 12), bool)
    a[0:4, 0:4] = True  # cells gx, gy in {0, 1}
    b = np.zeros((10, 12), bool)
    b[2:10, 2:6] = True  # cells gx in {1, 2}, gy in {1, 2, 3}
    near = occluder_map([(a, 0.8), (b, 0.5)], rows, cols, ks, stride)
    want = np.full((rows, cols), np.inf, np.float32)
    want[0:2, 0:2] = 0.8
    want[1:4, 1:3] = 0.5
    assert np.array_equal(near, want)
    with pytest.raises(PerchError, match="positive"):
        occluder_map([(a, 0.0)], rows, cols, ks, stride)
    with pytest.raises(PerchError, match="beta"):
        hidden_points(near, 1.5, 2, DEVICE)


def test_hide_kernel_marks_points_the_map_covers_nearer_than_their_candidate():
    rng = np.random.default_rng(5)
    rows, cols, ks, stride = 6, 7, 3, 2
    gboxes = np.array([[-1, -1, 4, 3], [2, 1, 5, 4], [0, 3, 3, 3]], np.int32)  # the first runs off the grid
    boxes = np.array([[0, 0, 20, 20]] * 3, np.int32)
    pts = point_layout(boxes, gboxes, ks, stride, DEVICE)
    near = np.where(rng.random((rows, cols)) < 0.5, rng.uniform(0.4, 1.2, (rows, cols)), np.inf).astype(np.float32)
    dist = np.array([0.8, 1.0, 0.6])
    n = pts.n_points
    blocks = 2
    vals = rng.normal(0, 1, blocks * n).astype(np.float32)
    vals[rng.random(len(vals)) < 0.2] = NOT_ON_MASK
    before = vals.copy()
    dev = wp.array(vals, dtype=float, device=DEVICE)
    t_m = np.zeros((3, 3))
    t_m[:, 2] = dist  # straight ahead: the translation's norm is the distance
    hide(dev, pts, t_m, hidden_points(near, 0.25, 1, DEVICE), blocks)
    got = dev.numpy()
    want = before.copy()
    i = 0
    for c, (gx0, gy0, gw, gh) in enumerate(gboxes):
        for gy in range(gy0, gy0 + gh):
            for gx in range(gx0, gx0 + gw):
                inside = 0 <= gx < cols and 0 <= gy < rows
                if inside and near[gy, gx] < dist[c]:
                    for s in range(blocks):
                        if want[s * n + i] != NOT_ON_MASK:
                            want[s * n + i] = HIDDEN
                i += 1
    assert np.array_equal(got, want) and (got == HIDDEN).sum() > 5


@pytest.fixture(scope="module")
def placed(random_weights):
    """The demo scene, its engine (the default score), and an occluder: the demo box itself at the
    candidate pose nearest the camera among a few around the truth, with the poses around it."""
    scene = demo_scene(seed=1)
    engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig())
    gx, gy, gyaw = scene.truth_xy_yaw
    rng = np.random.default_rng(1)
    x = gx + rng.uniform(-0.12, 0.12, 60)
    y = gy + rng.uniform(-0.12, 0.12, 60)
    yaw = rng.uniform(0, 2 * np.pi, 60)
    R, t = model_to_camera(scene.table, scene.resting, x, y, yaw)
    near = int(np.argmin(np.linalg.norm(t, axis=1)))
    T_occ = pose_matrix(R[near], t[near])
    keep = np.arange(60) != near
    return scene, engine, T_occ, (x[keep], y[keep], yaw[keep])


def test_scores_leave_out_the_points_an_occluder_covers_as_a_full_rendering_says(placed):
    """Score with hidden points = the NumPy reduction of each pose's point values with those under the
    occluder's full-image silhouette (looked up at each point's pixel, nearer than the pose's origin)
    marked hidden: an independent path to the grid map that kernel #2's values meet."""
    scene, engine, T_occ, poses = placed
    service = engine.scoring(scene.image, scene.camera, scene.table, scene.resting)
    hidden = engine.hidden_by(scene.camera, [(engine, T_occ)])
    assert isinstance(hidden, HiddenPoints) and hidden.occluders == 1
    fine = service.refining()
    values = fine.point_values(poses, pixels=True)
    _, occ_mask = engine.render(scene.camera, T_occ)
    d_occ = float(np.linalg.norm(T_occ[:3, 3]))
    _, t = model_to_camera(scene.table, scene.resting, *poses)
    marked, lens, any_hidden = [], [], []
    for (v, uv), d in zip(values, np.linalg.norm(t, axis=1), strict=True):
        inside = (uv[:, 0] < scene.camera.width) & (uv[:, 1] < scene.camera.height)
        hid = np.zeros(len(v), bool)
        hid[inside] = occ_mask[uv[inside, 1], uv[inside, 0]] & (d_occ < d)
        any_hidden.append(hid.any())
        marked.append(np.where(hid, np.float32(HIDDEN), v))
        lens.append(len(v))
    offsets = np.concatenate([[0], np.cumsum(lens)])
    ref, _ = top_alpha_mean(np.concatenate(marked), offsets, engine.config.alpha, beta=hidden.beta)
    got = dataclasses.replace(service, hidden=hidden).refining().score(poses)
    any_hidden = np.array(any_hidden)
    assert 5 <= any_hidden.sum() < len(lens) - 5  # some poses behind the occluder, some not
    assert np.array_equal(np.isfinite(ref), np.isfinite(got))
    ok = np.isfinite(ref)
    assert np.allclose(got[ok], ref[ok], rtol=0, atol=1e-6)
    plain = fine.score(poses)  # poses with no hidden point score as without the map, bit for bit
    assert np.array_equal(got[~any_hidden], plain[~any_hidden])
    assert np.sum(got[any_hidden] != plain[any_hidden]) >= 0.8 * any_hidden.sum()


def test_bound_stays_above_the_score_with_hidden_points(placed):
    scene, engine, T_occ, poses = placed
    service = engine.scoring(scene.image, scene.camera, scene.table, scene.resting)
    for beta in (0.0, 0.25, 1.0):
        s = dataclasses.replace(service, hidden=engine.hidden_by(scene.camera, [(engine, T_occ)], beta))
        scores, bounds = s.score(poses), s.bound(poses)  # the grid stage's score (shift tolerance)
        assert np.array_equal(np.isfinite(scores), np.isfinite(bounds))
        ok = np.isfinite(scores)
        assert ok.sum() > 30 and np.all(scores[ok] <= bounds[ok] + BOUND_SLACK)


def test_a_map_of_another_photo_size_is_refused(placed):
    scene, engine, _, _ = placed
    service = engine.scoring(scene.image, scene.camera, scene.table, scene.resting)
    wrong = hidden_points(np.full((3, 4), np.inf), 0.25, 0, DEVICE)
    with pytest.raises(PerchError, match="feature grid"):
        dataclasses.replace(service, hidden=wrong)
    assert math.isinf(float(wrong.near_m.numpy().min()))
