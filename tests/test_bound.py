"""The silhouette bound (kernels/bound.py) and the pruned search built on it."""

import math

import numpy as np
import pytest
import warp as wp
from _device import DEVICE
from perch_warp.kernels.features import NOT_ON_MASK

from perch_warp.bound import BOUND_SLACK, next_to_score, silhouette_bounds, silhouette_points
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.score import FeatureScorer, grid_boxes, grid_shape, top_alpha_mean
from perch_warp.score_terms import parse_score
from perch_warp.search_space import SearchSpace


@pytest.fixture(scope="module")
def scene():
    return demo_scene(seed=1)


def _space(scene, half=0.15, step=0.03, yaw_step_deg=30.0):
    """Holds the truth, off centre, and enough bare table that some bounds fall below the best score."""
    gx, gy, _ = scene.truth_xy_yaw
    cx, cy = round(gx / step) * step + step, round(gy / step) * step - step
    return SearchSpace(
        (cx - half, cx + half), (cy - half, cy + half), step, (0, 2 * math.pi), math.radians(yaw_step_deg)
    )


def _candidates(engine, scene, space, camera):
    """Poses, boxes and live candidates as the engine makes them, plus the photo's arrays."""
    service = engine.scoring(scene.image, camera, scene.table, scene.resting)
    c = service.candidates(*space.candidates())
    return service.photo, c.R[c.live], c.tr[c.live], c.boxes[c.live], c.gboxes[c.live]


RENDERERS = pytest.mark.parametrize("renderer", ["bvh", "raster"])


@RENDERERS
def test_points_are_the_rendered_masks_feature_points_with_their_rarity(scene, random_weights, renderer):
    """The bound's silhouette is the mask kernel #2 scores on, point for point, and its values are
    the photo's rarity there (0 beyond the photo): compared with the scorer's own output. Each form
    of kernel #1 has its own silhouette pass (any-hit BVH rays; the raster form's face tests)."""
    engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(renderer=renderer))
    # Some boxes run off the image so that points beyond the photo are exercised too.
    space = SearchSpace((-0.3, 0.3), (-0.3, 0.3), 0.15, (0, 2 * math.pi), math.radians(60))
    photo, R, t, boxes, gboxes = _candidates(engine, scene, space, scene.camera)
    ks, s = random_weights.kernel_size, engine.config.stride
    vals, off = silhouette_points(engine.renderer, scene.camera, R, t, boxes, gboxes, photo.ceiling, ks, s)
    batch = engine.renderer.render(scene.camera, R, t, boxes)
    svals, soff = engine.scorer.score_points(photo.image, batch, gboxes, photo.obs, photo.norm, photo.weights)
    v, sv = vals.numpy(), svals.numpy()
    assert np.array_equal(off.numpy(), soff.numpy())
    on = sv != NOT_ON_MASK
    assert np.array_equal(v != NOT_ON_MASK, on) and on.sum() > 100 and (~on).sum() > 100

    # Independent of both kernels: each point's grid cell, from the boxes alone.
    rar = photo.weights.gain.numpy()
    rows, cols = grid_shape(scene.camera.width, scene.camera.height, ks, s)
    want, outside = [], []
    for g in gboxes:
        gy, gx = np.mgrid[g[1] : g[1] + g[3], g[0] : g[0] + g[2]]  # the kernels' row-major point order
        inside = (gx >= 0) & (gy >= 0) & (gx < cols) & (gy < rows)
        want.append(np.where(inside, rar[np.clip(gy, 0, rows - 1), np.clip(gx, 0, cols - 1)], 0.0).ravel())
        outside.append(~inside.ravel())
    want, outside = np.concatenate(want), np.concatenate(outside)
    assert np.array_equal(v[on], want[on].astype(np.float32))
    assert (on & outside).any() and np.all(v[on & outside] == 0.0)


@RENDERERS
@pytest.mark.parametrize("alpha,relu", [(0.5, False), (0.35, False), (0.7, False), (0.5, True)])
def test_bound_is_never_below_the_score(scene, random_weights, renderer, alpha, relu):
    # --relu keeps no raw conv1 for the default score's centre term: its grid-tolerant part then.
    score = "grid-tolerant" if relu else EngineConfig().score
    config = EngineConfig(renderer=renderer, alpha=alpha, relu=relu, score=score)
    engine = Engine(scene.mesh, random_weights, DEVICE, config)
    photo, R, t, boxes, gboxes = _candidates(engine, scene, _space(scene), scene.camera)
    ks, s = random_weights.kernel_size, engine.config.stride
    bounds = silhouette_bounds(engine.renderer, scene.camera, R, t, boxes, gboxes, photo.ceiling, ks, s, alpha)
    batch = engine.renderer.render(scene.camera, R, t, boxes)
    vals, off = engine.scorer.score_points(photo.image, batch, gboxes, photo.obs, photo.norm, photo.weights)
    scores, _ = top_alpha_mean(vals.numpy(), off.numpy(), alpha)
    assert len(bounds) > 100 and np.all(np.isfinite(bounds) == np.isfinite(scores))
    ok = np.isfinite(scores)
    assert np.all(scores[ok] <= bounds[ok] + BOUND_SLACK)
    # And it is a bound worth having: not everything reaches the best score.
    assert np.mean(bounds[ok] >= scores[ok].max()) < 1.0


def test_next_to_score_takes_the_bounds_that_can_still_reach_the_threshold():
    ranked = np.array([0.9, 0.8, 0.7, 0.7, 0.5, 0.1])
    assert next_to_score(ranked, 0, -np.inf) == 6
    assert next_to_score(ranked, 1, 0.7) == 4  # ties with the threshold are scored
    assert next_to_score(ranked, 4, 0.7) == 4
    assert next_to_score(ranked, 0, 0.7 + BOUND_SLACK / 2) == 4  # within the slack: still scored
    assert next_to_score(ranked, 0, 2.0) == 0


@pytest.mark.parametrize("threads,renderer", [(1, "bvh"), (2, "raster")])
def test_pruned_search_returns_the_exhaustive_top_k_scoring_fewer(scene, caffe_weights, threads, renderer):
    space = _space(scene)
    args = (scene.image, scene.camera, scene.table, scene.resting, space)

    def run(search):
        config = EngineConfig(
            search=search, top_k=5, batch_pixels=20000, cpu_threads=threads, refine=False, renderer=renderer
        )
        return Engine(scene.mesh, caffe_weights, DEVICE, config).estimate(*args)

    full, pruned = run("exhaustive"), run("pruned")
    assert [(k.x_m, k.y_m, k.yaw_rad, k.score) for k in pruned.top_k] == [
        (k.x_m, k.y_m, k.yaw_rad, k.score) for k in full.top_k
    ]
    info = pruned.info.to_dict()  # the --out JSON's keys
    assert info["bounded"] == len(space) and info["scored"] == info["evaluated"] == pruned.n_scored
    assert info["rounds"] > 1 and info["scored"] < len(space)
    assert info["bound_rays"] > 0 and info["rays"] < full.info.rays
    assert "bound" in pruned.timings_s


@RENDERERS
def test_bound_kernel_runs_on_empty_input(random_weights, renderer):
    """No candidates: no launch, no error (a batch can come out empty at the end of a round)."""
    scene = demo_scene(seed=1)
    engine = Engine(scene.mesh, random_weights, DEVICE, EngineConfig(renderer=renderer))
    scorer = FeatureScorer(random_weights, DEVICE, 4)
    rarity = wp.zeros((2, 2), dtype=float, device=DEVICE)
    empty = np.zeros((0, 4), np.int32)
    out = silhouette_bounds(
        engine.renderer,
        scene.camera,
        np.zeros((0, 3, 3)),
        np.zeros((0, 3)),
        empty,
        grid_boxes(empty, 11, 4),
        rarity,
        scorer.ks,
        4,
        0.5,
    )
    assert out.shape == (0,)


def test_pyramid_bounds_change_nothing_but_the_work(scene, caffe_weights):
    """Coarse-to-fine leaves out lattice points whose bound cannot reach the beam: the same
    answer as scoring them all, every top-k candidate and score equal, fewer scored."""
    space = _space(scene, half=0.15, step=0.01, yaw_step_deg=30.0)
    args = (scene.image, scene.camera, scene.table, scene.resting, space)

    def run(bounds: bool):
        config = EngineConfig(
            search="coarse-to-fine", beam=8, top_k=5, pyramid_bounds=bounds, batch_pixels=20000, refine=False
        )
        return Engine(scene.mesh, caffe_weights, DEVICE, config).estimate(*args)

    plain, bounded = run(False), run(True)
    assert [(k.x_m, k.y_m, k.yaw_rad, k.score) for k in bounded.top_k] == [
        (k.x_m, k.y_m, k.yaw_rad, k.score) for k in plain.top_k
    ]
    assert bounded.info.evaluated < plain.info.evaluated and "bound" in bounded.timings_s


class _RecordingBar:
    """Stands in for tqdm: records the count after every update."""

    def __init__(self, total=0, **_):
        self.total, self.n, self.seen = total, 0, []

    def update(self, n):
        assert n > 0
        self.n += n
        self.seen.append(self.n)

    def refresh(self):
        pass

    def close(self):
        pass


def test_pruned_progress_counts_ruled_out_candidates_when_they_are_ruled_out(scene, caffe_weights, monkeypatch):
    """The bar's time left must follow where the search ends: after each round it counts as done the
    scored candidates and those whose bound fell below the threshold, so the last round ends it."""
    import tqdm

    bars = []
    monkeypatch.setattr(tqdm, "tqdm", lambda *a, **kw: bars.append(_RecordingBar(**kw)) or bars[-1])
    config = EngineConfig(search="pruned", top_k=5, batch_pixels=20000, cpu_threads=1, refine=False)
    r = Engine(scene.mesh, caffe_weights, DEVICE, config).estimate(
        scene.image, scene.camera, scene.table, scene.resting, _space(scene), progress=True
    )
    (bar,) = bars
    assert bar.total == bar.n == r.info.extra["bounded"]
    assert r.info.extra["scored"] < r.info.extra["bounded"] and r.info.extra["rounds"] > 1
    # One update per round: a candidate ruled out is counted in the round that rules it out, none at the end.
    assert len(bar.seen) == r.info.extra["rounds"]
    assert bar.seen[-1] == bar.total


@pytest.mark.parametrize(
    "score",
    [
        "surround=fill",
        "surround=weighted",
        "background=0.7",
        "shrink=12",
        "rarity=total,inits=2",
        "surround=fill,background=0.5,shrink=8",
        "shift=1",
        "shift=2,background=0.5,surround=weighted",
        "outline=1.0",
        "outline=0.3,shift=1,background=0.5",
        "table=0.5,shift=1",
        "texture=mip,shift=1",
        "light=1.0",
        "light=0.5,texture=mip,shift=1",
        "rectified=0.5",
        "rectified=1.0,shift=1",
        "exposure=1",
        "exposure=0.5,shift=1,surround=fill",
        "tone=2",
        "tone=1,shift=1,surround=fill",
        "smooth=1.5,shift=1",
        "shade=0.8,shift=1",
        "centre=0.5",
        "centre=1.0,shift=1,surround=weighted",
        "centred",
        "centred-4starts",
        "centred-direction",
    ],
)
def test_bound_is_admissible_for_every_score(scene, caffe_weights, score):
    """bound >= score for every candidate of random poses, whatever the score's terms (score_terms'
    proof: value <= gain - offset pointwise, the same k and divisor)."""
    space = _space(scene, half=0.06, step=0.03, yaw_step_deg=60.0)
    engine = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(score=score))
    out = engine.bounds_and_scores(scene.image, scene.camera, scene.table, scene.resting, space)
    live = np.isfinite(out["score"])
    assert live.sum() > 10
    assert np.all(out["bound"][live] >= out["score"][live] - BOUND_SLACK)
    # Not vacuous: some bound is close to its score. The outline term's part of the bound is its weight
    # times the largest edge within a stride, near 1 in a textured photo (perch_warp.outline): looser by it.
    assert np.min(out["bound"][live] - out["score"][live]) < 0.5 + parse_score(score)[1].outline


@pytest.mark.parametrize(
    "score",
    [
        "surround=fill,background=0.5,shrink=8",
        "shift=1,shrink=8",
        "outline=0.3,shift=1,shrink=8",
        "table=0.5,shift=1",
        "light=1.0,texture=mip,shift=1",
        "rectified=0.5,shift=1",
        "exposure=1,shift=1",
        "tone=2,shift=1",
        "shade=0.8,shift=1",
        "centred",
        "centred-4starts",
        "centred-direction",
    ],
)
def test_pruned_equals_exhaustive_under_a_new_score(scene, caffe_weights, score):
    """The pruned search stays exact when the score has every new term: the same top-k poses and scores."""
    space = _space(scene)

    def run(search):
        config = EngineConfig(score=score, search=search, batch_pixels=20000, cpu_threads=1, refine=False)
        return Engine(scene.mesh, caffe_weights, DEVICE, config).estimate(
            scene.image, scene.camera, scene.table, scene.resting, space
        )

    runs = {s: run(s) for s in ("exhaustive", "pruned")}
    a, b = runs["exhaustive"], runs["pruned"]
    assert [(c.x_m, c.y_m, c.yaw_rad) for c in a.top_k] == [(c.x_m, c.y_m, c.yaw_rad) for c in b.top_k]
    assert np.allclose([c.score for c in a.top_k], [c.score for c in b.top_k], rtol=0, atol=1e-9)
    assert a.info.score == b.info.score == parse_score(score)[0]
    # The outline term's bound is looser by up to its weight (perch_warp.outline): in this small space
    # it rules nothing out, so only its exactness is checked; every other term prunes here.
    assert b.info.extra["scored"] < len(space) or parse_score(score)[1].outline > 0


def test_footing_prior_is_each_candidates_own_footing(scene, caffe_weights):
    """The footing term, computed once per place, adds to each candidate w times its own place's footing."""
    from perch_warp.footing import footing, footprint_radius_m

    space = _space(scene, half=0.06, step=0.03, yaw_step_deg=60.0)
    engine = Engine(scene.mesh, caffe_weights, DEVICE, EngineConfig(score="table=0.5"))
    service = engine.scoring(scene.image, scene.camera, scene.table, scene.resting)
    x, y, yaw = space.candidates()
    c = service.candidates(x, y, yaw)
    radius = footprint_radius_m(service.backends.boxes.hull_m, scene.resting)
    ks, stride = service.backends.weights.kernel_size, service.config.stride
    own = [
        footing(scene.table, scene.camera, service.photo.likeness, x[i], y[i], radius, ks, stride)[0]
        for i in range(len(x))
    ]
    assert len(set(np.round(own, 12))) > 1  # not vacuous: the places' footings differ
    np.testing.assert_array_equal(c.prior, 0.5 * np.array(own))
