import math

import numpy as np
import pytest
import warp as wp
from _device import DEVICE
from perch_warp.kernels.features import NOT_ON_MASK

from perch_warp.score import alpha_count, top_alpha_mean, top_alpha_mean_device


def test_top_alpha_mean_matches_sorting_each_candidate():
    rng = np.random.default_rng(0)
    counts = rng.integers(0, 40, 30)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    values = rng.normal(size=offsets[-1])
    values[rng.random(offsets[-1]) < 0.3] = NOT_ON_MASK
    for alpha in (0.1, 0.5, 0.77, 1.0):
        got, n = top_alpha_mean(values.astype(np.float32), offsets, alpha)
        for c in range(len(counts)):
            v = values[offsets[c] : offsets[c + 1]]
            v = np.sort(v[v != NOT_ON_MASK].astype(np.float32))[::-1]
            assert n[c] == len(v)
            if len(v) == 0:
                assert got[c] == -np.inf
            else:
                k = max(1, math.ceil(alpha * len(v)))
                assert np.isclose(got[c], v[:k].mean(), atol=1e-6)


def test_alpha_one_is_the_plain_mean_and_counts_round_up():
    got, _ = top_alpha_mean(np.array([1.0, 2.0, 3.0, 6.0]), np.array([0, 4]), 1.0)
    assert got[0] == 3.0
    assert alpha_count(0.5, 5) == 3 and alpha_count(0.5, 4) == 2 and alpha_count(0.01, 3) == 1


def _segments_with_edge_cases(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Flat float32 values and offsets: random segments, heavy ties, and the corner cases up front."""
    segments = [
        np.zeros(0, np.float32),  # empty box
        np.full(5, NOT_ON_MASK, np.float32),  # no point on the mask
        np.array([0.25], np.float32),  # a single point
        np.array([NOT_ON_MASK, -0.5, NOT_ON_MASK], np.float32),  # a single on-mask point
        np.full(9, 0.125, np.float32),  # all tied
        np.array([1.0, 1.0, -1.0, -1.0, 0.0, 0.0], np.float32),  # ties straddling any k
        np.array([3e-38, 0.0, -3e-38, 1e-45, -1e-45], np.float32),  # tiny magnitudes: bisection near zero
        np.array([2.0, 1.0, 0.0, -1.0, -2.0], np.float32),
    ]
    for n in rng.integers(1, 400, 150):
        v = rng.normal(size=n).astype(np.float32)
        if rng.random() < 0.5:
            v = np.round(v, 1).astype(np.float32)  # few distinct values: many ties
        v[rng.random(n) < 0.1] = 0.0  # silhouette beyond the photo's grid scores exactly 0
        v[rng.random(n) < rng.random()] = NOT_ON_MASK
        segments.append(v)
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in segments])]).astype(np.int32)
    return np.concatenate(segments).astype(np.float32), offsets


@pytest.mark.parametrize("alpha", [1e-6, 0.1, 0.3, 0.5, 0.77, 1.0])
def test_device_top_alpha_mean_equals_numpy_reference(alpha):
    values, offsets = _segments_with_edge_cases(np.random.default_rng(11))
    ref, ref_n = top_alpha_mean(values, offsets, alpha)
    scores, n = top_alpha_mean_device(
        wp.array(values, dtype=wp.float32, device=DEVICE), wp.array(offsets, dtype=wp.int32, device=DEVICE), alpha
    )
    got, got_n = scores.numpy(), n.numpy()
    assert got.dtype == np.float64 and np.array_equal(got_n, ref_n)
    empty = ref_n == 0
    assert empty[:2].all() and np.all(got[empty] == -np.inf)
    assert np.allclose(got[~empty], ref[~empty], rtol=0, atol=1e-6)
    # k = 1 is the maximum, k = n the plain mean: both cases occur above.
    ks = np.array([alpha_count(alpha, int(m)) for m in ref_n[~empty]])
    assert (ks == 1).any() and (ks == ref_n[~empty]).any()


def test_device_top_alpha_mean_of_no_candidates():
    values = wp.zeros(0, dtype=wp.float32, device=DEVICE)
    scores, n = top_alpha_mean_device(values, wp.array(np.zeros(1, np.int32), device=DEVICE), 0.5)
    assert scores.shape == (0,) and n.shape == (0,)


def test_cudnn_full_precision_turns_tf32_off_for_the_block_only():
    """The torch form's settings on a GPU (they are flags, so they can be checked without one): no
    TF32 and deterministic cuDNN inside, torch's own defaults back afterwards."""
    torch = pytest.importorskip("torch")
    from perch_warp.score import cudnn_full_precision

    cudnn = torch.backends.cudnn
    before = (cudnn.allow_tf32, cudnn.deterministic, cudnn.benchmark)
    precision = getattr(getattr(cudnn, "conv", None), "fp32_precision", None)
    with cudnn_full_precision():
        assert cudnn.allow_tf32 is False and cudnn.deterministic is True and cudnn.benchmark is False
        if precision is not None:  # torch >= 2.9 reads the new setting for convolutions
            assert cudnn.conv.fp32_precision == "ieee"
    assert (cudnn.allow_tf32, cudnn.deterministic, cudnn.benchmark) == before
    if precision is not None:
        assert cudnn.conv.fp32_precision == precision


def test_conv_settings_apply_inside_the_block_only(caffe_weights):
    """The torch form's one-thread setting holds inside `with`, not from the call on, and is undone after."""
    torch = pytest.importorskip("torch")
    from perch_warp.score import FeatureScorer

    before = torch.get_num_threads()
    settings = FeatureScorer(caffe_weights, DEVICE, 4, conv="torch").conv_settings()
    assert torch.get_num_threads() == before
    with settings:
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("shrink", [0.0, 3.0, 16.0])
def test_shrink_divides_the_top_sum_by_k_plus_k0(shrink):
    """The size-aware score (score_terms' shrink): host and device give sum(top k) / (k + k0)."""
    values, offsets = _segments_with_edge_cases(np.random.default_rng(5))
    alpha = 0.5
    got, n = top_alpha_mean(values, offsets, alpha, shrink)
    dev, _ = top_alpha_mean_device(
        wp.array(values, dtype=wp.float32, device=DEVICE),
        wp.array(offsets, dtype=wp.int32, device=DEVICE),
        alpha,
        shrink,
    )
    for c in range(len(offsets) - 1):
        v = values[offsets[c] : offsets[c + 1]]
        v = np.sort(v[v != NOT_ON_MASK].astype(np.float64))[::-1]
        if len(v) == 0:
            assert got[c] == -np.inf and dev.numpy()[c] == -np.inf
            continue
        k = alpha_count(alpha, len(v))
        assert np.isclose(got[c], v[:k].sum() / (k + shrink), atol=1e-6)
        assert np.isclose(dev.numpy()[c], got[c], rtol=0, atol=1e-6)


def test_point_values_reduce_to_the_scores_the_engine_computes(random_weights):
    """ScoringService.point_values (the values tools/score_study.py keeps to study other reductions):
    each pose's values, reduced by the NumPy top-α mean, give the score the engine's own path (the
    device's reduction) gives; a pose that shows no feature point has none; the grid stage's
    shift-tolerant score, several values per point, is refused with a message that says why."""
    from perch_warp.demo import demo_scene
    from perch_warp.engine import Engine, EngineConfig
    from perch_warp.errors import PerchError

    scene = demo_scene(seed=1)
    engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="centred", alpha=0.4))
    service = engine.scoring(scene.image, scene.camera, scene.table, scene.resting)
    gx, gy, gyaw = scene.truth_xy_yaw
    rng = np.random.default_rng(0)
    x = np.concatenate([[gx, 4.0], gx + rng.uniform(-0.1, 0.1, 10)])
    y = np.concatenate([[gy, 4.0], gy + rng.uniform(-0.1, 0.1, 10)])
    yaw = np.concatenate([[gyaw, 0.0], rng.uniform(0, 2 * np.pi, 10)])
    with pytest.raises(PerchError, match="one value per point"):
        service.point_values((x, y, yaw))
    fine = service.refining()
    values = fine.point_values((x, y, yaw))
    scores = fine.score((x, y, yaw))
    assert len(values[1]) == 0 and scores[1] == -np.inf  # 4 m away: off the image
    lens = np.array([len(v) for v in values])
    assert np.all(lens[np.isfinite(scores)] > 50)
    ref, n = top_alpha_mean(np.concatenate(values), np.concatenate([[0], np.cumsum(lens)]), 0.4)
    assert np.array_equal(n, lens)
    assert np.allclose(ref[np.isfinite(scores)], scores[np.isfinite(scores)], rtol=0, atol=1e-6)
    assert np.all(np.isneginf(ref[~np.isfinite(scores)]))


def test_point_pixels_lie_on_the_pose_rendered_whole(random_weights):
    """point_values(pixels=True): the same values, each with its photo pixel, on the feature grid (11 x 11
    windows, stride 4: 5 + 4 g) and inside the pose's silhouette in a full-image rendering of that pose
    (an independent path: Engine.render of the whole camera image, not the candidate's crop)."""
    from perch_warp.demo import demo_scene
    from perch_warp.engine import Engine, EngineConfig
    from perch_warp.table import model_to_camera, pose_matrix

    scene = demo_scene(seed=1)
    engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(score="centred"))
    fine = engine.scoring(scene.image, scene.camera, scene.table, scene.resting).refining()
    gx, gy, gyaw = scene.truth_xy_yaw
    x, y, yaw = np.array([gx, gx + 0.03, 4.0]), np.array([gy, gy - 0.02, 4.0]), np.array([gyaw, gyaw + 1.0, 0.0])
    plain = fine.point_values((x, y, yaw))
    with_uv = fine.point_values((x, y, yaw), pixels=True)
    R, t = model_to_camera(scene.table, scene.resting, x, y, yaw)
    for i in range(3):
        v, uv = with_uv[i]
        assert np.array_equal(v, plain[i]) and uv.shape == (len(v), 2) and uv.dtype == np.int32
        if i == 2:  # off the image: no points
            assert len(v) == 0
            continue
        assert len(v) > 50 and np.all((uv - 5) % 4 == 0)
        _, mask = engine.render(scene.camera, pose_matrix(R[i], t[i]))
        assert np.all((uv[:, 0] >= 0) & (uv[:, 0] < scene.camera.width) & (uv[:, 1] >= 0))
        assert mask[uv[:, 1], uv[:, 0]].mean() > 0.98  # the crop's and the whole image's rays agree
