"""Rarity of the photo's appearance (thesis §3.2.2): rare features count more, like TF-IDF."""

from __future__ import annotations

import numpy as np
from sklearn.cluster import KMeans
from threadpoolctl import threadpool_limits


def rarity_from_labels(labels: np.ndarray, n_clusters: int, mode: str = "max") -> np.ndarray:
    """1 - (frequency of the point's cluster / frequency of the most frequent cluster) for mode
    "max" (the thesis's: the commonest appearance weighs 0, the rarest close to 1), or
    1 - (frequency / number of points) for mode "total" (the commonest weighs what it leaves)."""
    counts = np.bincount(labels, minlength=n_clusters).astype(np.float64)
    norm = counts.max() if mode == "max" else counts.sum()
    return (1.0 - counts[labels] / norm).astype(np.float32)


def unit_responses(features: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """(N, C) float32: each raw conv1 feature (N, C) without conv1's folded bias (C,), scaled to unit
    length (0 where it vanishes). conv1 is W x + b on the window x (RGB in [0, 1], the preprocessing
    folded into W and b), so W x scales with the window's brightness and its direction does not:
    clustered, a shadowed face joins its lit twin rather than the shadows (score term ``cluster``)."""
    g = np.asarray(features, np.float64) - np.asarray(bias, np.float64)[None, :]
    n = np.linalg.norm(g, axis=1, keepdims=True)
    return np.divide(g, n, out=np.zeros_like(g), where=n > 1e-9).astype(np.float32)


def kmeans_labels(features: np.ndarray, n_clusters: int = 20, seed: int = 0, inits: int = 1) -> np.ndarray:
    """k-means cluster of each feature vector (N, C), the best of `inits` initialisations;
    deterministic for a seed, on any machine (one thread, see below)."""
    n_clusters = int(min(n_clusters, len(features)))
    km = KMeans(n_clusters=n_clusters, n_init=inits, random_state=seed)
    # scikit-learn splits k-means' sums over OpenMP threads, and another split can move a point to
    # another cluster: on the seed-0 image 1/11 the same pose scored 0.878937 with one thread (a
    # one-CPU Ray worker) and 0.878805 with two. One thread makes the rarity, and so the answer, the
    # same on every machine, core count and worker.
    with threadpool_limits(limits=1):
        return km.fit_predict(np.asarray(features, dtype=np.float32)).astype(np.int64)


def rarity(features: np.ndarray, n_clusters: int = 20, seed: int = 0, mode: str = "max", inits: int = 1) -> np.ndarray:
    """Rarity in [0, 1) of every feature vector (N, C) of one photo."""
    return rarity_and_labels(features, n_clusters, seed, mode, inits)[0]


def rarity_and_labels(
    features: np.ndarray, n_clusters: int = 20, seed: int = 0, mode: str = "max", inits: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """(rarity (N,), k-means labels (N,)) of the feature vectors (N, C)."""
    labels = kmeans_labels(features, n_clusters, seed, inits)
    return rarity_from_labels(labels, int(labels.max()) + 1, mode), labels
