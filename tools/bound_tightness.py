"""How tight is the pruned search's silhouette bound? Every candidate's bound against its score.

    python tools/bound_tightness.py [--dataset DIR --scene 2 --image 1 --obj 9] [--half 0.15]
        [--xy-step 0.02] [--yaw-step 30] [--top-k 5] [--device cpu] [--image-scale 1]

Searches a square of half-width --half (m) around the object's ground-truth position (off
centre by one step, so the truth is on the grid but not in the middle), scores *every*
candidate and bounds it, and prints: bound violations (must be 0), the best scores, the
bound and score quantiles, and the fraction of candidates the pruned search must score
(bound >= k-th best score). The engine is perch_warp's own; nothing is pruned here.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from perch_warp import bench
from perch_warp.bound import BOUND_SLACK
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.features import load_feature_weights
from perch_warp.search_space import SearchSpace


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    bench.add_frame_arguments(ap)
    ap.add_argument("--half", type=float, default=0.15, help="half-width of the square around the truth, m")
    ap.add_argument("--xy-step", type=float, default=0.02, help="x/y step, m (default 0.02)")
    ap.add_argument("--yaw-step", type=float, default=30.0, help="yaw step, degrees (default 30)")
    ap.add_argument("--top-k", type=int, default=5, help="k of the pruned search's threshold (default 5)")
    ap.add_argument("--device", default="cpu", help="Warp device (default: cpu)")
    ap.add_argument("--image-scale", type=float, default=1.0)
    ap.add_argument("--weights", default="caffe")
    args = ap.parse_args(argv)
    try:
        dataset = args.dataset or bench.default_dataset()
        if dataset is None:
            raise PerchError("no --dataset given and shared/data/ycbv not found (set PERCH_WARP_SHARED)")
        if not args.half >= 1.5 * args.xy_step > 0:
            raise PerchError(f"--half must be at least 1.5 x --xy-step to hold the truth, got {args.half}")
        w = bench.load_workload(dataset, args.scene, args.image, args.obj, 1.0, args.xy_step, 0.1)
        gx, gy, _ = w.truth_xy_yaw
        s = args.xy_step
        cx, cy = round(gx / s) * s + s, round(gy / s) * s - s
        h = args.half
        space = SearchSpace((cx - h, cx + h), (cy - h, cy + h), s, (0, 2 * math.pi), math.radians(args.yaw_step))
        config = EngineConfig(top_k=args.top_k, image_scale=args.image_scale)
        engine = Engine(w.mesh, load_feature_weights(args.weights), args.device, config)
        r = engine.bounds_and_scores(w.image, w.camera, w.table, w.resting, space)
    except PerchError as e:
        print(f"bound_tightness: error: {e}", file=sys.stderr)
        return 1
    b, sc = r["bound"], r["score"]
    ok = np.isfinite(sc)
    kth = np.sort(sc[ok])[::-1][: args.top_k]
    q = (0.1, 0.5, 0.9)
    print(f"{w.label}; {space.describe()}; image scale {args.image_scale:g}, {args.device}")
    print(f"candidates with feature points  {int(ok.sum())} of {len(sc)}")
    print(f"bound below score (violations)  {int((sc[ok] > b[ok] + BOUND_SLACK).sum())}")
    print(f"best scores                     {', '.join(f'{v:.4f}' for v in kth)}")
    print(f"score quantiles 10/50/90 %      {', '.join(f'{v:.3f}' for v in np.quantile(sc[ok], q))}")
    print(f"bound quantiles 10/50/90 %      {', '.join(f'{v:.3f}' for v in np.quantile(b[ok], q))}")
    need = float(np.mean(b[ok] >= kth[-1] - BOUND_SLACK))
    print(f"must be scored (bound >= {args.top_k}th best) {100 * need:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
