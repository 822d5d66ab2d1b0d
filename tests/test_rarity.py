import numpy as np

from perch_warp.rarity import kmeans_labels, rarity, rarity_from_labels


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


def _inertia(feats: np.ndarray, labels: np.ndarray) -> float:
    """Sum of squared distances of the points to their cluster's mean (k-means' objective), in NumPy."""
    return float(sum(((feats[labels == c] - feats[labels == c].mean(0)) ** 2).sum() for c in np.unique(labels)))


def test_several_kmeans_starts_keep_the_best_clustering():
    # Twelve blobs of unequal size for eight clusters: one k-means start often settles in a worse
    # local minimum. `inits` starts include the single start's (same seed), so the objective can only
    # fall, and it does fall for some seeds.
    rng = np.random.default_rng(1)
    centres = rng.normal(0, 3, (12, 6))
    sizes = rng.integers(20, 200, 12)
    feats = np.concatenate([rng.normal(c, 0.5, (n, 6)) for c, n in zip(centres, sizes, strict=True)])
    feats = feats.astype(np.float32)
    one = [_inertia(feats, kmeans_labels(feats, 8, seed, 1)) for seed in range(6)]
    four = [_inertia(feats, kmeans_labels(feats, 8, seed, 4)) for seed in range(6)]
    assert all(b <= a * (1 + 1e-6) for a, b in zip(one, four, strict=True))
    assert sum(b < a * (1 - 1e-3) for a, b in zip(one, four, strict=True)) >= 2
    again = kmeans_labels(feats, 8, 3, 4)
    assert np.array_equal(again, kmeans_labels(feats, 8, 3, 4))
