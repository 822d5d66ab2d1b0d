import numpy as np

from perch_warp.rarity import kmeans_labels, rarity, rarity_from_labels, unit_responses


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


def test_unit_responses_drop_the_bias_and_ignore_brightness():
    """unit_responses: (F - b) / |F - b|, so conv1 features of a window and of the same window at 30 %
    of its brightness (F = b + W x and b + 0.3 W x, conv1 being linear) have one direction."""
    rng = np.random.default_rng(2)
    W, b = rng.normal(0, 1, (5, 16)), rng.normal(0, 2, 16)
    x = rng.uniform(0, 1, (40, 5))
    lit, dark = x @ W + b, 0.3 * x @ W + b
    u = unit_responses(lit, b)
    ref = (lit - b) / np.linalg.norm(lit - b, axis=1, keepdims=True)
    assert u.dtype == np.float32 and np.allclose(u, ref, atol=1e-6)
    assert np.allclose(unit_responses(dark, b), u, atol=1e-6)
    assert not np.allclose(dark / np.linalg.norm(dark, axis=1, keepdims=True), ref, atol=1e-2)  # raw: not so
    assert np.array_equal(unit_responses(np.tile(b, (3, 1)), b), np.zeros((3, 16), np.float32))  # no response


def test_direction_clusters_put_a_shadowed_face_with_its_lit_twin():
    """The harsh-light failure the term is for: the commonest raw cluster is the shadows, and it takes in
    the face turned from the light (rarity 0); clustered on directions, the face joins its lit twin and
    the shadows' own cluster keeps the weight 0."""
    rng = np.random.default_rng(4)
    W, b = rng.normal(0, 1, (6, 12)), rng.normal(0, 1, 12)
    shade = 0.05 * rng.uniform(0.9, 1.1, (700, 6))  # cast shadows: dark, the most common appearance
    table = rng.uniform(0, 1, 6) * rng.uniform(0.95, 1.05, (500, 6))  # the lit table
    face = rng.uniform(0, 1, 6)  # a printed face, lit and in shadow
    lit = face * rng.uniform(0.95, 1.05, (60, 6))
    dim = 0.08 * face * rng.uniform(0.95, 1.05, (60, 6))
    F = np.concatenate([shade, table, lit, dim]) @ W + b
    raw = rarity(F.astype(np.float32), n_clusters=3, seed=0)
    unit = rarity(unit_responses(F, b), n_clusters=3, seed=0)
    assert raw[1260:].max() == 0.0 and raw[:700].max() == 0.0  # the dim face weighs 0 with the shadows
    assert unit[1200:].min() > 0.8 and unit[:700].max() == 0.0


def test_kmeans_runs_on_one_thread_whatever_the_machine(monkeypatch):
    # How scikit-learn splits k-means' sums over OpenMP threads can move a point to another cluster,
    # so the fit must see one thread even where the caller allows more (a many-core GPU machine).
    from threadpoolctl import threadpool_info, threadpool_limits

    import perch_warp.rarity as rarity_module

    seen: list[int] = []
    fit_predict = rarity_module.KMeans.fit_predict

    def spy(self, *args, **kwargs):
        seen.extend(p["num_threads"] for p in threadpool_info() if p["user_api"] == "openmp")
        return fit_predict(self, *args, **kwargs)

    monkeypatch.setattr(rarity_module.KMeans, "fit_predict", spy)
    feats = np.random.default_rng(1).normal(0, 1, (500, 8)).astype(np.float32)
    with threadpool_limits(limits=2):
        labels = kmeans_labels(feats, n_clusters=6, seed=0, inits=2)
    assert seen, "no OpenMP thread pool seen during the k-means fit"
    assert set(seen) == {1}
    assert np.array_equal(labels, kmeans_labels(feats, n_clusters=6, seed=0, inits=2))
