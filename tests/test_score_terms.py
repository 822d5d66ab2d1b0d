"""Score terms (perch_warp.score_terms): parsing, and the background offset against its definition."""

import numpy as np
import pytest

from perch_warp.errors import PerchError
from perch_warp.rarity import rarity_from_labels
from perch_warp.score_terms import DEFAULT_SCORE, SCORES, ScoreTerms, background_offset, parse_score


def test_names_and_terms_parse():
    assert parse_score("thesis") == ("thesis", ScoreTerms())
    name, terms = parse_score("surround=fill, shrink=16,background=0.5")
    assert terms == ScoreTerms(surround="fill", shrink=16.0, background=0.5)
    assert name == "surround=fill,background=0.5,shrink=16.0"
    assert parse_score("shrink=0")[0] == "thesis"  # the thesis's terms, however written
    assert parse_score("shift=1,shrink=8") == ("shrink=8.0,shift=1", ScoreTerms(shrink=8.0, shift=1))
    assert set(SCORES) >= {"thesis", "grid-tolerant", DEFAULT_SCORE}
    assert parse_score("grid-tolerant") == ("grid-tolerant", ScoreTerms(shift=1))
    assert parse_score("centred") == ("centred", ScoreTerms(shift=1, centre=0.5))
    assert parse_score("centred-4starts") == ("centred-4starts", ScoreTerms(shift=1, centre=0.5, inits=4))
    assert parse_score("centred-direction") == (
        "centred-direction",
        ScoreTerms(shift=1, centre=0.5, inits=4, cluster="direction"),
    )
    assert parse_score("shift=1,outline=0.25") == ("shift=1,outline=0.25", ScoreTerms(shift=1, outline=0.25))


@pytest.mark.parametrize(
    "spec, culprit",
    [
        ("nonsense", "nonsense"),
        ("colour=red", "colour"),
        ("shrink=abc", "shrink"),
        ("shrink=-1", "shrink"),
        ("surround=blur", "surround"),
        ("background=2", "background"),
        ("rarity=median", "rarity"),
        ("inits=0", "inits"),
        ("cluster=colour", "cluster"),
        ("shift=4", "shift"),
        ("shift=-1", "shift"),
        ("shift=0.5", "shift"),
        ("outline=1.5", "outline"),
        ("outline=-0.1", "outline"),
        ("outline=nan", "outline"),
        ("table=2", "table"),
        ("light=2", "light must be in"),
        ("light=-0.5", "light must be in"),
        ("light=nan", "light must be in"),
        ("texture=nearest", "texture must be one of"),
        ("rectified=1.5", "rectified must be in"),
        ("rectified=nan", "rectified must be in"),
        ("exposure=3", "exposure must be 0 to"),
        ("exposure=0.3", "half stops"),
        ("exposure=nan", "exposure must be 0 to"),
        ("exposure=1,light=0.5", "cannot be combined"),
        ("tone=4", "tone must be 0 to"),
        ("tone=-1", "tone must be 0 to"),
        ("tone=1.5", "tone needs a int"),
        ("tone=1,exposure=0.5", "cannot be combined"),
        ("tone=1,light=0.5", "cannot be combined"),
        ("smooth=4", "smooth must be 0 to"),
        ("smooth=-1", "smooth must be 0 to"),
        ("smooth=nan", "smooth must be 0 to"),
        ("shade=1.5", "shade must be in"),
        ("shade=-0.1", "shade must be in"),
        ("shade=nan", "shade must be in"),
        ("centre=1.5", "centre must be in"),
        ("centre=nan", "centre must be in"),
        ("centre=0.5,exposure=1", "centre cannot be combined"),
        ("centre=0.5,rectified=0.5", "centre cannot be combined"),
    ],
)
def test_bad_terms_name_the_culprit(spec, culprit):
    with pytest.raises(PerchError, match=culprit):
        parse_score(spec)


def test_rarity_modes():
    labels = np.array([0, 0, 0, 1, 1, 2])
    assert np.allclose(rarity_from_labels(labels, 3, "max"), [0, 0, 0, 1 / 3, 1 / 3, 2 / 3])
    assert np.allclose(rarity_from_labels(labels, 3, "total"), [0.5, 0.5, 0.5, 2 / 3, 2 / 3, 5 / 6])


def test_background_offset_is_weighted_cosine_to_the_commonest_centroid():
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(50, 8))
    labels = rng.integers(0, 4, 50)
    labels[:20] = 2  # cluster 2 is the commonest
    gain = rng.random(50).astype(np.float32)
    got = background_offset(feats, labels, gain, 0.7)
    B = feats[labels == 2].mean(0)
    for i in range(50):
        cos = feats[i] @ B / (np.linalg.norm(feats[i]) * np.linalg.norm(B))
        assert got[i] == pytest.approx(0.7 * gain[i] * max(cos, 0.0), abs=1e-6)
    assert np.all(background_offset(feats, labels, gain, 0.0) == 0)
    assert np.all(gain - got >= 0)  # the ceiling gain - offset stays >= 0 for weights <= 1


def test_cluster_direction_rarity_is_kmeans_on_conv1s_unbiased_unit_response(random_weights):
    """cluster=direction: the photo's gain is the thesis's rarity of the unit vectors of conv1's response
    without its bias, here from torch's conv on x / std with no bias (conv1 on (x - mean) / std plus the
    bias, less the folded bias, is that); the thesis's clustering of the same photo weighs otherwise."""
    import torch
    from _device import DEVICE

    from perch_warp.demo import demo_scene
    from perch_warp.engine import Engine, EngineConfig
    from perch_warp.rarity import rarity, unit_responses

    scene = demo_scene(seed=1)
    gains = {}
    for cluster in ("features", "direction"):
        config = EngineConfig(score=f"shift=1,inits=2,cluster={cluster}")
        service = Engine(scene.mesh, random_weights, DEVICE, config).scoring(
            scene.image, scene.camera, scene.table, scene.resting
        )
        photo = service.photo
        gains[cluster] = photo.weights.gain.numpy().ravel()
    obs = photo.obs.numpy().reshape(photo.rows * photo.cols, -1)
    x = torch.from_numpy(scene.image.astype(np.float64) / 255.0).permute(2, 0, 1)[None]
    std = torch.tensor(random_weights.std, dtype=torch.float64)[None, :, None, None]
    g = torch.nn.functional.conv2d(x / std, torch.from_numpy(random_weights.weight).double(), stride=4)
    g = g[0].permute(1, 2, 0).reshape(photo.rows * photo.cols, -1).numpy()
    u = unit_responses(obs, service.backends.scorer.folded_bias)
    assert np.abs(u - g / np.linalg.norm(g, axis=1, keepdims=True)).max() < 1e-3
    config = service.config
    assert np.array_equal(gains["direction"], rarity(u, config.clusters, config.seed, "max", 2))
    assert not np.allclose(gains["direction"], gains["features"], atol=0.05)


def test_cluster_direction_needs_raw_conv1(random_weights):
    from _device import DEVICE

    from perch_warp.demo import demo_scene
    from perch_warp.engine import Engine, EngineConfig

    with pytest.raises(PerchError, match="cluster=direction.*drop --relu"):
        Engine(demo_scene(seed=1).mesh, random_weights, DEVICE, EngineConfig(score="cluster=direction", relu=True))
