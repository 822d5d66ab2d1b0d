"""Which BVH build renders fastest? The engine's render kernel on one batch, per Warp BVH option.

    python tools/bvh_options.py [--device cpu|cuda:0] [--poses 300] [--clip 0.3]
        [--constructors sah median lbvh] [--leaf-sizes 1 2 4 8]

The batch: the first --poses candidates of the reference frame's visible-table grid (clip
--clip m, 2 cm, 0.5 rad) whose boxes are in the image. Each option builds a new `wp.Mesh`
over the same points, renders the batch once untimed and --repeat times timed (the fastest
counts), and must give the
same mask and colours as the first option (a BVH changes the work, not the answer).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import warp as wp

from perch_warp import bench
from perch_warp.errors import PerchError
from perch_warp.render import BvhRenderer, DeviceMesh, project_boxes
from perch_warp.table import model_to_camera


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    bench.add_frame_arguments(ap)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--poses", type=int, default=300)
    ap.add_argument("--clip", type=float, default=0.3)
    ap.add_argument("--constructors", nargs="+", default=["sah", "median", "lbvh"])
    ap.add_argument("--leaf-sizes", nargs="+", type=int, default=[1, 2, 4, 8])
    ap.add_argument("--repeat", type=int, default=3, help="timed renders per option; the fastest counts (default 3)")
    args = ap.parse_args(argv)
    try:
        dataset = args.dataset or bench.default_dataset()
        if dataset is None:
            raise PerchError("no --dataset given and shared/data/ycbv not found (set PERCH_WARP_SHARED)")
        w = bench.load_workload(dataset, args.scene, args.image, args.obj, args.clip, 0.02, 0.5)
    except PerchError as e:
        print(f"bvh_options: error: {e}", file=sys.stderr)
        return 1
    wp.config.log_level = wp.LOG_WARNING
    x, y, yaw = w.space.candidates()
    R, t = model_to_camera(w.table, w.resting, x, y, yaw)
    boxes = project_boxes(w.camera, w.mesh.hull_points_m(), R, t)
    ok = np.flatnonzero((boxes[:, 2] > 0) & (boxes[:, 3] > 0))[: args.poses]
    R, t, boxes = R[ok], t[ok], boxes[ok]
    renderer = BvhRenderer(DeviceMesh(w.mesh, args.device))
    n_rays = int((boxes[:, 2].astype(np.int64) * boxes[:, 3]).sum())
    print(f"{w.label}; {len(ok)} poses, {n_rays:,} rays, {len(w.mesh.faces)} faces, device {args.device}")
    ref = None
    for cons in args.constructors:
        if cons == "lbvh" and wp.get_device(args.device).is_cpu:
            print("lbvh: not built on the CPU (Warp falls back to SAH there)")
            continue
        for leaf in args.leaf_sizes:
            try:
                with wp.ScopedDevice(args.device):
                    dm = renderer.dmesh  # the same BVH renderer over a BVH built another way
                    renderer.wp_mesh = wp.Mesh(
                        points=dm.points, indices=dm.indices, bvh_constructor=cons, bvh_leaf_size=leaf
                    )
            except (RuntimeError, ValueError) as e:
                print(f"{cons:<7} leaf {leaf}: not available ({e})")
                continue
            renderer.render(w.camera, R, t, boxes)
            wp.synchronize_device(args.device)
            dt = float("inf")
            for _ in range(max(1, args.repeat)):
                t0 = time.perf_counter()
                b = renderer.render(w.camera, R, t, boxes)
                wp.synchronize_device(args.device)
                dt = min(dt, time.perf_counter() - t0)
            m, c = b.mask.numpy(), b.rgb.numpy()
            ref = ref or (m, c)
            same = np.array_equal(m, ref[0]) and np.array_equal(c, ref[1])
            print(f"{cons:<7} leaf {leaf}: {dt:.4f} s, {n_rays / dt / 1e6:.2f} M rays/s, same image: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
