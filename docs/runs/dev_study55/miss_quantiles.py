# The best right pose's and the best wrong pose's (top-0.5 mean) point values, for the development misses.
# Run from the repository root: python miss_q.py VALUES_DIR
import sys

import numpy as np

sys.path.insert(0, "tools")
import score_study as ss  # noqa: E402

for k in ["1_12_0", "1_7_0", "1_40_2", "1_6_1", "1_32_3"]:
    z = np.load(f"{sys.argv[1]}/values_{k}.npz")
    sc = ss.reduce_values(z["values"], z["lens"], ["top0.5"])["top0.5"]
    right = z["adds_m"] < 0.02
    i = np.flatnonzero(right)[np.argmax(sc[right])]
    j = np.flatnonzero(~right)[np.argmax(sc[~right])]
    off = np.concatenate([[0], np.cumsum(z["lens"])])
    for name, p in (("truth", i), ("answer", j)):
        v = np.sort(z["values"][off[p] : off[p + 1]])[::-1]
        q = np.round(np.quantile(v, [0.9, 0.75, 0.5, 0.25, 0.1]), 3)
        best = v[: max(1, len(v) // 10)].mean()
        print(f"{k} {name:6s} n {len(v):4d}  percentiles 90/75/50/25/10 {q}  best 10 % {best:.3f}")
