"""Peak re-ranking (perch_warp.peaks and the engine's refine_peaks)."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.peaks import (
    YAW_SEPARATION_STEPS,
    distinct_peaks,
    kth_location_score,
    peak_pool,
    top_location_candidates,
    yaw_peaks,
)
from perch_warp.refine import cell_space
from perch_warp.score_terms import parse_score
from perch_warp.search_space import SearchSpace

# The score the refinement below the grid uses: the default's terms less the grid's shift.
REFINE_SCORE = parse_score(EngineConfig().score)[1].below_grid().spec()


@pytest.fixture(scope="module")
def scene():
    return demo_scene()


def _brute(cands, n, sxy):
    """Greedy NMS of locations written out: best first, keep unless within sxy in x and y of a kept one."""
    kept = []
    for i, c in enumerate(cands):
        close = any(abs(c[0] - cands[j][0]) <= sxy + 1e-9 and abs(c[1] - cands[j][1]) <= sxy + 1e-9 for j in kept)
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
            assert distinct_peaks(cands, n, 0.02) == _brute(cands, n, 0.02)


def test_yaw_variants_of_one_place_are_one_peak():
    cands = [(0.0, 0.0, 0.0, 1.0), (0.0, 0.01, math.pi, 0.95), (0.05, 0.0, 0.0, 0.9)]
    assert distinct_peaks(cands, 3, 0.03) == [0, 2]


def test_pool_grows_only_with_peaks():
    assert peak_pool(5, 1) == 5 and peak_pool(5, 4) == 128 and peak_pool(200, 2) == 200


def test_locations_by_their_best_yaw_against_brute_force():
    rng = np.random.default_rng(1)
    n_yaw = 6
    flat = np.sort(rng.choice(40 * n_yaw, 150, replace=False))
    scores = np.round(rng.random(150), 2)  # ties
    scores[rng.random(150) < 0.1] = -np.inf
    pos = top_location_candidates(flat, scores, n_yaw, 7)
    best = {}
    for p, (f, s) in enumerate(zip(flat, scores, strict=True)):
        loc = f // n_yaw
        if np.isfinite(s) and (loc not in best or s > scores[best[loc]]):
            best[loc] = p  # flat ascending: the first of equal scores is the lower index
    ref = sorted(best.values(), key=lambda p: (-scores[p], flat[p]))[:7]
    assert pos.tolist() == ref
    kth = sorted((scores[p] for p in best.values()), reverse=True)[6]
    assert kth_location_score(flat, scores, n_yaw, 7) == kth
    assert kth_location_score(flat, scores, n_yaw, 10_000) == -np.inf


def test_refined_peaks_win_over_the_grid_best_alone(scene, caffe_weights):
    """With several peaks the answer is the best of their refined cells, each refined as the single-peak
    search refines its own best: never below the one-peak answer, and equal to refining each peak alone."""
    space = SearchSpace((-0.12, 0.12), (-0.12, 0.12), 0.03, (0, 2 * math.pi), math.radians(45))
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    fine = dict(refine_xy_m=0.01, refine_yaw_rad=math.radians(15), search="exhaustive", cpu_threads=1)
    one = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(**fine)).estimate(*args)
    many = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(refine_peaks=3, **fine)).estimate(*args)
    peaks = many.info.extra["refine"]["peaks"]
    assert 1 <= len(peaks) <= 3 and many.score >= one.score - 1e-12
    assert many.score == max(p["score"] for p in peaks)
    # Each peak's refined score is the best score of its cell, scored pose by pose, under the score the
    # refinement uses: the default's without the grid's shift tolerance.
    e = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(**{**fine, "score": REFINE_SCORE}))
    for p in peaks:
        f = p["from"]
        yaw = math.radians(f["yaw_deg"])
        cell = cell_space(space, f["x_m"], f["y_m"], yaw, fine["refine_xy_m"], fine["refine_yaw_rad"])
        direct = e.score(scene.image, scene.camera, scene.table, scene.resting, *cell.candidates())
        assert abs(direct.max() - p["score"]) < 1e-9
    assert len(many.top_k) == 5 and many.top_k[0].score == many.score


def test_pruned_keeps_the_exhaustive_best_locations(scene, caffe_weights):
    """With several peaks the pruned search ranks locations exactly: the same refined peaks and answer as
    the exhaustive search (on this small space every bound reaches the 64th location, so the exactness of
    the pruning itself rests on kth_location_score, tested above, being the threshold)."""
    space = SearchSpace((-0.15, 0.15), (-0.15, 0.15), 0.02, (0, 2 * math.pi), math.radians(30))
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    fine = dict(refine_xy_m=0.01, refine_yaw_rad=math.radians(15), refine_peaks=2, top_k=1, cpu_threads=1)
    runs = {
        s: Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(search=s, batch_pixels=20000, **fine)).estimate(*args)
        for s in ("exhaustive", "pruned")
    }
    a, b = runs["exhaustive"], runs["pruned"]
    assert a.info.extra["refine"]["peaks"] == b.info.extra["refine"]["peaks"] and a.score == b.score
    assert b.info.extra["k"] == 64  # the rank of the location whose score a bound had to reach


def _brute_yaw_peaks(s, m, circular, first):
    """yaw_peaks written out: local maxima (wrapping when circular), best first, ties to the lower index,
    each more than YAW_SEPARATION_STEPS from every one kept."""
    n = len(s)

    def at(i):
        return s[i % n] if circular or 0 <= i < n else -np.inf

    def dist(i, j):
        return min(abs(i - j), n - abs(i - j)) if circular else abs(i - j)

    local = [i for i in range(n) if np.isfinite(s[i]) and s[i] >= at(i - 1) and s[i] >= at(i + 1)]
    kept = [] if first is None else [first]
    for i in sorted(local, key=lambda i: (-s[i], i)):
        if len(kept) < m and all(dist(i, j) > YAW_SEPARATION_STEPS for j in kept):
            kept.append(i)
    return kept[:m]


def test_yaw_peaks_equal_brute_force():
    rng = np.random.default_rng(2)
    for _ in range(200):
        n = int(rng.integers(1, 30))
        s = np.round(rng.random(n), 1)  # ties
        s[rng.random(n) < 0.15] = -np.inf
        circular = bool(rng.integers(0, 2))
        first = int(rng.integers(0, n)) if rng.random() < 0.5 else None
        for m in (1, 2, 4):
            assert yaw_peaks(s, m, circular, first) == _brute_yaw_peaks(s, m, circular, first)


def test_yaw_peaks_wrap_on_the_full_circle():
    s = np.array([0.9, 0.1, 0.2, 0.3, 0.2, 0.1, 0.5, 1.0])  # index 7's neighbours: 6 and 0
    assert yaw_peaks(s, 3, True) == [7, 3]  # across the wrap 0's neighbour 7 is higher: 0 is no peak
    assert yaw_peaks(s, 3, False) == [7, 0, 3]  # on an open range 0 and 7 are far apart


def test_refine_yaws_refines_each_yaw_peak_of_the_place(scene, caffe_weights):
    """With several yaws per place, every grid yaw of the peak's place is scored and its best yaw peaks are
    refined: the answer is the best of those cells (scored pose by pose here), never below one yaw's."""
    space = SearchSpace((-0.12, 0.12), (-0.12, 0.12), 0.03, (0, 2 * math.pi), math.radians(30))
    args = (scene.image, scene.camera, scene.table, scene.resting, space)
    fine = dict(refine_xy_m=0.01, refine_yaw_rad=math.radians(10), search="exhaustive", cpu_threads=1, top_k=1)
    one = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(**fine)).estimate(*args)
    e = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(refine_yaws=3, **fine))
    many = e.estimate(*args)
    (peak,) = many.info.extra["refine"]["peaks"]
    assert len(peak["yaws_deg"]) >= 2 and many.score >= one.score - 1e-12
    f = one.info.extra["refine"]["from"]  # the place's grid best, refined first
    assert peak["yaws_deg"][0] == pytest.approx(f["yaw_deg"])
    yaws = space.axes()[2]
    place = (np.full(len(yaws), f["x_m"]), np.full(len(yaws), f["y_m"]), yaws)
    at_place = e.score(scene.image, scene.camera, scene.table, scene.resting, *place)
    first = int(np.argmin(np.abs(yaws - math.radians(f["yaw_deg"]))))
    chosen = yaw_peaks(at_place, 3, True, first)
    assert [round(math.degrees(yaws[i]), 6) for i in chosen] == [round(v, 6) for v in peak["yaws_deg"]]
    best = -np.inf
    # Below the grid: the default score without its grid shift.
    plain = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(**{**fine, "score": REFINE_SCORE}))
    for i in chosen:
        cell = cell_space(space, f["x_m"], f["y_m"], float(yaws[i]), fine["refine_xy_m"], fine["refine_yaw_rad"])
        best = max(best, plain.score(scene.image, scene.camera, scene.table, scene.resting, *cell.candidates()).max())
    assert abs(best - many.score) < 1e-9
