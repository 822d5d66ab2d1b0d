"""Rarity of the photo's appearance (thesis §3.2.2): rare features count more, like TF-IDF."""

from __future__ import annotations

import numpy as np


def rarity_from_labels(labels: np.ndarray, n_clusters: int) -> np.ndarray:
    """1 - (frequency of the point's cluster / frequency of the most frequent cluster).

    The commonest appearance weighs 0, the rarest close to 1.
    """
    counts = np.bincount(labels, minlength=n_clusters).astype(np.float64)
    return (1.0 - counts[labels] / counts.max()).astype(np.float32)


def kmeans_labels(features: np.ndarray, n_clusters: int = 20, seed: int = 0) -> np.ndarray:
    """k-means cluster of each feature vector (N, C); deterministic for a seed."""
    from sklearn.cluster import KMeans

    n_clusters = int(min(n_clusters, len(features)))
    km = KMeans(n_clusters=n_clusters, n_init=1, random_state=seed)
    return km.fit_predict(np.asarray(features, dtype=np.float32)).astype(np.int64)


def rarity(features: np.ndarray, n_clusters: int = 20, seed: int = 0) -> np.ndarray:
    """Rarity in [0, 1) of every feature vector (N, C) of one photo."""
    labels = kmeans_labels(features, n_clusters, seed)
    return rarity_from_labels(labels, int(labels.max()) + 1)
