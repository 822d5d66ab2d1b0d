"""The scoring service and each search through their public interfaces (perch_warp.search)."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp import search as searches
from perch_warp.bound import BOUND_SLACK
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.search import refine
from perch_warp.search.base import top_indices
from perch_warp.search.scoring import PoseSource, SearchStats
from perch_warp.search_space import SearchSpace


@pytest.fixture(scope="module")
def scene():
    return demo_scene(seed=1)


@pytest.fixture(scope="module")
def space(scene):
    gx, gy, _ = scene.truth_xy_yaw
    return SearchSpace((gx - 0.04, gx + 0.04), (gy - 0.04, gy + 0.04), 0.02, (0, 2 * math.pi), math.radians(45))


@pytest.fixture(scope="module")
def engine(scene, random_weights):
    cfg = EngineConfig(search="exhaustive", top_k=5, refine=False, renderer="raster", batch_pixels=20000)
    return Engine(scene.mesh, random_weights, DEVICE, cfg)


@pytest.fixture(scope="module")
def service(engine, scene, space):
    return engine.scoring(scene.image, scene.camera, scene.table, scene.resting, space)


def test_service_scores_known_poses_as_the_engine_does(engine, service, scene, space):
    """score() of the engine's top-k poses gives the engine's scores bit for bit; bound() is above them;
    the cost is counted in the SearchStats passed, not kept by the service."""
    res = engine.estimate(scene.image, scene.camera, scene.table, scene.resting, space)
    x, y, yaw = (np.array([getattr(c, a) for c in res.top_k]) for a in ("x_m", "y_m", "yaw_rad"))
    stats = SearchStats()
    scores = service.score((x, y, yaw), stats)
    assert scores.tolist() == [c.score for c in res.top_k]
    c = service.candidates(x, y, yaw)
    assert stats.rays == int((c.boxes[c.live, 2].astype(np.int64) * c.boxes[c.live, 3]).sum()) > 0
    assert stats.batches >= 1 and stats.bound_rays == 0
    bounds = service.bound(PoseSource.of_arrays(x, y, yaw), stats)
    assert np.all(scores <= bounds + BOUND_SLACK) and stats.bound_rays > 0
    # A fresh stats object per call: nothing carried over on the service.
    again = SearchStats()
    assert service.score((x, y, yaw), again).tolist() == scores.tolist() and again.rays == stats.rays


def test_searches_are_chosen_by_name_and_agree(service, space, engine):
    assert set(searches.SEARCHES) == {"exhaustive", "pruned", "coarse-to-fine"}
    ex = searches.get("exhaustive")(service, space)
    pr = searches.get("pruned")(service, space)
    assert ex.flat is None and ex.evaluated == len(space) and pr.evaluated == pr.extra["scored"]
    k = engine.config.top_k
    top = top_indices(ex.scores, k)
    assert top_indices(pr.scores, k).tolist() == top.tolist()
    assert pr.scores[top].tolist() == ex.scores[top].tolist()  # the same kernels: bit for bit
    assert pr.stats.bound_rays == pr.extra["bound_rays"] > 0 and ex.stats.bound_rays == 0
    c2f = searches.get("coarse-to-fine")(service, space)
    assert c2f.flat is not None and np.all(np.diff(c2f.flat) > 0) and "levels" in c2f.extra
    finite = np.isfinite(c2f.scores)
    assert c2f.scores[finite].tolist() == ex.scores[c2f.flat[finite]].tolist()
    assert c2f.flat[int(np.argmax(c2f.scores))] == top[0]  # finds the best here


def test_refine_and_probe_through_the_service(service, space):
    ex = searches.get("exhaustive")(service, space)
    i = top_indices(ex.scores, 3)
    x, y, yaw = space.at(i)
    top = [(float(x[n]), float(y[n]), float(yaw[n]), float(ex.scores[j])) for n, j in enumerate(i)]
    refined, info = refine.refine(service, space, top, "exhaustive")
    assert refined[0][3] >= top[0][3] and info["score_gain"] == refined[0][3] - top[0][3]
    assert info["search"] == "exhaustive" and info["rays"] > 0 and info["evaluated"] <= info["candidates"]
    assert "refine" in service.timings
    probed = refine.probe(service, space, top[0][:3], "pruned")
    assert probed["score"] == pytest.approx(refined[0][3], abs=1e-12)  # the same cell, searched pruned
