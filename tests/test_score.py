import math

import numpy as np
from perch_warp.kernels.features import NOT_ON_MASK

from perch_warp.score import alpha_count, top_alpha_mean


def test_top_alpha_mean_matches_sorting_each_candidate():
    rng = np.random.default_rng(0)
    counts = rng.integers(0, 40, 30)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    values = rng.normal(size=offsets[-1])
    values[rng.random(offsets[-1]) < 0.3] = NOT_ON_MASK
    for alpha in (0.1, 0.5, 0.77, 1.0):
        got, n = top_alpha_mean(values.astype(np.float32), offsets, alpha)
        for c in range(len(counts)):
            v = values[offsets[c] : offsets[c + 1]]
            v = np.sort(v[v != NOT_ON_MASK].astype(np.float32))[::-1]
            assert n[c] == len(v)
            if len(v) == 0:
                assert got[c] == -np.inf
            else:
                k = max(1, math.ceil(alpha * len(v)))
                assert np.isclose(got[c], v[:k].mean(), atol=1e-6)


def test_alpha_one_is_the_plain_mean_and_counts_round_up():
    got, _ = top_alpha_mean(np.array([1.0, 2.0, 3.0, 6.0]), np.array([0, 4]), 1.0)
    assert got[0] == 3.0
    assert alpha_count(0.5, 5) == 3 and alpha_count(0.5, 4) == 2 and alpha_count(0.01, 3) == 1
