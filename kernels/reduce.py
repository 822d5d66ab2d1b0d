"""The top-α mean on the device: one thread per candidate, so one float per candidate leaves it.

Candidate c owns values[offsets[c]:offsets[c+1]] (kernel #2's feature-point scores);
entries at or below NOT_ON_MASK / 2 are off its mask. The values may be several blocks laid out
alike (kernel #2 under shifts: block s is values[s N : (s + 1) N], N = offsets[n_cand]); thread
j = s n_cand + c reduces candidate c of block s. Its score is the mean of the
top k = max(1, ceil(α n - 1e-9)) of its n on-mask values (perch_warp.score.alpha_count;
perch_warp.score.top_alpha_mean is the NumPy reference), -inf when n = 0.

Points another object hides (HIDDEN, kernels/hidden.py) stay part of the silhouette: with V of the
n points visible, k = max(1, ceil(α m - 1e-9)) for m = max(V, ceil(β n - 1e-9)), and the score is the
sum of the best min(k, V) visible values over k (+ shrink): a candidate almost wholly behind another
object (V < β n) counts each missing point as 0, so it cannot win on a few points; -inf when V = 0.
Without hidden points (V = n) m = n, and the arithmetic is the plain top-α mean's, bit for bit.

Selection is exact: with t the k-th largest value, the top-k sum is
sum(v > t) + (k - count(v > t)) t, whatever the ties. t is found by bisection of a
value interval [lo, hi] that always holds it, with both ends snapped to values of the
candidate after each pass, so every pass drops at least one distinct value and halves
the interval; a pass also stops the search when the value it snapped to is t (counts
of the values equal to it say so). About 10 passes for 800 points on real data,
never more than the number of distinct values. No scratch memory, no sorting.
"""

import warp as wp

from .features import NOT_ON_MASK
from .hidden import HIDDEN_BELOW

# No fused multiply-adds: k = ceil(α n - 1e-9) must round as the host's alpha_count does.
wp.set_module_options({"fuse_fp": False})

# On-mask values lie above this (kernel #2 writes NOT_ON_MASK elsewhere).
OFF_MASK_BELOW = NOT_ON_MASK / 2.0


@wp.kernel(enable_backward=False)
def top_alpha_mean(
    values: wp.array(dtype=wp.float32),
    offsets: wp.array(dtype=wp.int32),
    n_cand: int,
    alpha: wp.float64,
    shrink: wp.float64,
    beta: wp.float64,
    out_score: wp.array(dtype=wp.float64),
    out_n: wp.array(dtype=wp.int32),
):
    j = wp.tid()
    c = j % n_cand
    base = (j // n_cand) * offsets[n_cand]
    start = base + offsets[c]
    end = base + offsets[c + 1]
    n = int(0)
    nv = int(0)  # visible: not hidden by another object
    vmin = float(wp.inf)
    vmax = float(-wp.inf)
    for i in range(start, end):
        v = values[i]
        if v > OFF_MASK_BELOW:
            n += 1
            if v > HIDDEN_BELOW:
                nv += 1
                vmin = wp.min(vmin, v)
                vmax = wp.max(vmax, v)
    out_n[j] = n
    if nv == 0:
        out_score[j] = wp.float64(-wp.inf)
        return
    m = n
    if nv < n:
        m = wp.max(nv, int(wp.ceil(beta * wp.float64(n) - wp.float64(1.0e-9))))
    # The same float64 formula as alpha_count, so k agrees with the host bit for bit.
    k = wp.max(1, int(wp.ceil(alpha * wp.float64(m) - wp.float64(1.0e-9))))
    kv = wp.min(k, nv)  # the visible values summed; k > nv only when beta n > nv

    # Invariant: lo <= t <= hi, both values of this candidate. kv = nv and kv = 1 need no search.
    lo = vmin
    hi = vmax
    if kv == nv:
        hi = vmin
    if kv == 1:
        lo = vmax
    while lo < hi:
        mid = wp.min(0.5 * lo + 0.5 * hi, hi)
        if mid <= lo:  # lo and hi are adjacent floats: test hi itself
            mid = hi
        n_ge = int(0)
        min_ge = float(wp.inf)  # the least value >= mid, and how many equal it
        n_min_ge = int(0)
        max_lt = float(-wp.inf)  # the greatest value < mid, and how many equal it
        n_max_lt = int(0)
        for i in range(start, end):
            v = values[i]
            if v > HIDDEN_BELOW:
                if v >= mid:
                    n_ge += 1
                    if v < min_ge:
                        min_ge = v
                        n_min_ge = 1
                    elif v == min_ge:
                        n_min_ge += 1
                elif v > max_lt:
                    max_lt = v
                    n_max_lt = 1
                elif v == max_lt:
                    n_max_lt += 1
        if n_ge >= kv:
            lo = min_ge  # t >= mid, and t is one of the values >= mid
            if n_ge - n_min_ge < kv:  # fewer than kv lie above min_ge: it is t
                hi = lo
        else:
            hi = max_lt  # t < mid, and t is one of the values < mid
            if n_ge + n_max_lt >= kv:  # at least kv lie at or above max_lt: it is t
                lo = hi
    t = lo

    # float64 sums, as the host reference takes them.
    n_gt = int(0)
    total = wp.float64(0.0)
    for i in range(start, end):
        v = values[i]
        if v > HIDDEN_BELOW and v > t:
            n_gt += 1
            total += wp.float64(v)
    out_score[j] = (total + wp.float64(kv - n_gt) * wp.float64(t)) / (wp.float64(k) + shrink)
