"""What every search shares: its outcome, and picking the best of scored candidates."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .scoring import SearchStats


@dataclass
class Outcome:
    """A search's scores over the space: scores[i] is candidate i of the space, or grid candidate
    flat[i] when flat is given (a search that scores a subset); -inf where not scored. `evaluated`:
    candidates scored; `stats`: what it cost; `extra`: the search's own facts for the result.
    `bounds` (the pruned search): every candidate's silhouette bound, -inf where it shows no feature
    point; a candidate left unscored (score -inf, bound finite) scores at most its bound
    (+ bound.BOUND_SLACK), which is what perch_warp.score_map needs to tell pruned from invisible."""

    scores: np.ndarray
    evaluated: int
    stats: SearchStats
    flat: np.ndarray | None = None
    extra: dict = field(default_factory=dict)
    bounds: np.ndarray | None = None


def auto_search(device: str) -> str:
    """What --search auto runs: pruned on the CPU (measured faster there), exhaustive on a GPU (not measured)."""
    return "pruned" if wp.get_device(device).is_cpu else "exhaustive"


def top_indices(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k largest scores, best first, ties to the lower index: the first k of a
    stable argsort of -scores, without sorting the whole space."""
    if len(scores) > k:
        kth = np.partition(scores, len(scores) - k)[len(scores) - k]
        idx = np.flatnonzero(scores >= kth)
    else:
        idx = np.arange(len(scores))
    return idx[np.argsort(-scores[idx], kind="stable")][:k]


def kth_largest(values: np.ndarray, k: int) -> float:
    """The k-th largest of values; -inf when there are fewer than k (nothing can be ruled out yet)."""
    n = len(values)
    return float(np.partition(values, n - k)[n - k]) if 0 < k <= n else -np.inf
