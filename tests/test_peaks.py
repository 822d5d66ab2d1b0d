"""Peak re-ranking (perch_warp.peaks and the engine's refine_peaks)."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.peaks import distinct_peaks, peak_pool
from perch_warp.refine import cell_space
from perch_warp.search_space import SearchSpace


@pytest.fixture(scope="module")
def scene():
    return demo_scene()


def _brute(cands, n, sxy, syaw):
    """Greedy NMS written out: walk best first, keep a candidate unless within the box of a kept one."""
    kept = []
    for i, c in enumerate(cands):
        close = False
        for j in kept:
            d = cands[j]
            dyaw = min(abs(c[2] - d[2]) % (2 * math.pi), 2 * math.pi - abs(c[2] - d[2]) % (2 * math.pi))
            if abs(c[0] - d[0]) <= sxy + 1e-9 and abs(c[1] - d[1]) <= sxy + 1e-9 and dyaw <= syaw + 1e-9:
                close = True
        if not close and len(kept) < n:
            kept.append(i)
    return kept


def test_distinct_peaks_equal_brute_force_nms():
    rng = np.random.default_rng(0)
    for _ in range(30):
        m = int(rng.integers(1, 60))
        xy = rng.integers(-5, 6, (m, 2)) * 0.01
        yaw = rng.integers(0, 72, m) * math.radians(5)
        score = np.sort(rng.random(m))[::-1]
        cands = [(float(a), float(b), float(c), float(d)) for (a, b), c, d in zip(xy, yaw, score, strict=True)]
        for n in (1, 3, 8):
            assert distinct_peaks(cands, n, 0.02, math.radians(10)) == _brute(cands, n, 0.02, math.radians(10))


def test_yaw_wraps_around_the_circle():
    cands = [(0.0, 0.0, math.radians(358), 1.0), (0.0, 0.0, math.radians(3), 0.9), (0.0, 0.0, math.radians(20), 0.8)]
    assert distinct_peaks(cands, 3, 0.02, math.radians(10)) == [0, 2]


def test_pool_grows_only_with_peaks():
    assert peak_pool(5, 1) == 5 and peak_pool(5, 4) == 128 and peak_pool(200, 2) == 200


def test_refined_peaks_win_over_the_grid_best_alone(scene, caffe_weights):
    """With several peaks the answer is the best of their refined cells, each refined as the single-peak
    search refines its own best: never below the one-peak answer, and equal to refining each peak alone."""
    space = SearchSpace((-0.12, 0.12), (-0.12, 0.12), 0.03, (0, 2 * math.pi), math.radians(45))
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    fine = dict(refine_xy_m=0.01, refine_yaw_rad=math.radians(15), search="exhaustive", cpu_threads=1)
    one = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(**fine)).estimate(*args)
    many = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(refine_peaks=3, **fine)).estimate(*args)
    peaks = many.info["refine"]["peaks"]
    assert 2 <= len(peaks) <= 3 and many.score >= one.score - 1e-12
    assert many.score == max(p["score"] for p in peaks)
    # Each peak's refined score is the best score of its cell, scored pose by pose.
    e = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(**fine))
    for p in peaks:
        f = p["from"]
        yaw = math.radians(f["yaw_deg"])
        cell = cell_space(space, f["x_m"], f["y_m"], yaw, fine["refine_xy_m"], fine["refine_yaw_rad"])
        direct = e.score(scene.image, scene.camera, scene.table, scene.resting, *cell.candidates())
        assert abs(direct.max() - p["score"]) < 1e-9
    assert len(many.top_k) == 5 and many.top_k[0].score == many.score
