import numpy as np

from perch_warp.rarity import rarity, rarity_from_labels


def test_rarity_follows_its_definition():
    labels = np.array([0, 0, 0, 0, 1, 1, 2])
    r = rarity_from_labels(labels, 3)
    assert np.allclose(r, [0, 0, 0, 0, 0.5, 0.5, 0.75])


def test_kmeans_rarity_is_deterministic_and_weighs_rare_appearance():
    rng = np.random.default_rng(0)
    common = rng.normal(0, 0.1, (900, 8))
    rare = rng.normal(5, 0.1, (30, 8))
    feats = np.concatenate([common, rare]).astype(np.float32)
    a = rarity(feats, n_clusters=4, seed=3)
    b = rarity(feats, n_clusters=4, seed=3)
    assert np.array_equal(a, b)
    assert a.min() == 0.0 and a.max() < 1.0
    assert a[900:].mean() > 0.9 > a[:900].mean()
