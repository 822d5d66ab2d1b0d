"""Accuracy and cost of the feature stride (issue: pick the default by measured accuracy).

Runs the engine at several strides on (a) demo scenes (procedural, shaded, noisy) and
(b) the real YCB-Video frame shared/data/ycbv/test/000002 (objects 1 and 9), each over a
small square that contains the ground truth off-centre, and prints ADD-S and time.

    python tools/stride_study.py [--strides 1 2 4] [--device cpu] [--out stride_study.json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import time

import numpy as np

from perch_warp.camera import camera_from_entry
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.features import load_feature_weights
from perch_warp.image import load_rgb
from perch_warp.mesh import load_mesh
from perch_warp.paths import shared_dir
from perch_warp.pose_error import adi
from perch_warp.search_space import SearchSpace
from perch_warp.table import Table, decompose_on_table, model_to_camera


def square_around(x: float, y: float, half: float, step: float, yaw_step_deg: float) -> SearchSpace:
    cx, cy = round(x / step) * step + step, round(y / step) * step - step
    return SearchSpace(
        (cx - half, cx + half), (cy - half, cy + half), step, (0, 2 * math.pi), math.radians(yaw_step_deg)
    )


def cases(n_demo: int):
    for seed in range(n_demo):
        sc = demo_scene(seed=seed)
        gx, gy, gyaw = sc.truth_xy_yaw
        R, t = model_to_camera(sc.table, sc.resting, gx, gy, gyaw)
        yield (
            f"demo seed {seed}",
            sc.mesh,
            sc.image,
            sc.camera,
            sc.table,
            sc.resting,
            R[0],
            t[0],
            square_around(gx, gy, 0.05, 0.01, 15.0),
        )
    root = shared_dir()
    if root is None:
        return
    d = root / "data" / "ycbv" / "test" / "000002"
    image = load_rgb(d / "rgb" / "000001.png")
    entry = json.loads((d / "scene_camera.json").read_text())["1"]
    camera = camera_from_entry(entry, image.shape[1], image.shape[0])
    table = Table.from_entry(entry)
    for g in json.loads((d / "scene_gt.json").read_text())["1"]:
        if g["obj_id"] not in (1, 9):
            continue
        R, t = np.reshape(g["cam_R_m2c"], (3, 3)), np.asarray(g["cam_t_m2c"]) / 1000
        resting, gx, gy, _ = decompose_on_table(table, R, t)
        mesh = load_mesh(root / "data" / "ycbv" / "models" / f"obj_{g['obj_id']:06d}.obj")
        yield (
            f"ycbv 000002 obj {g['obj_id']}",
            mesh,
            image,
            camera,
            table,
            resting,
            R,
            t,
            square_around(gx, gy, 0.03, 0.01, 10.0),
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--strides", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--demo-scenes", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--weights", default="caffe")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    weights = load_feature_weights(args.weights)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    rows = []
    print(f"device {args.device} ({platform.processor() or platform.machine()}), commit {commit}, {weights.source}")
    print("| case | candidates | " + " | ".join(f"stride {s}: ADD-S cm / s" for s in args.strides) + " |")
    print("|---|---|" + "---|" * len(args.strides))
    for name, mesh, image, camera, table, resting, R, t, space in cases(args.demo_scenes):
        cells = []
        for s in args.strides:
            eng = Engine(mesh, weights, args.device, EngineConfig(stride=s, search="exhaustive", refine=False))
            t0 = time.perf_counter()
            r = eng.estimate(image, camera, table, resting, space)
            dt = time.perf_counter() - t0
            e = adi(r.T_m2c[:3, :3], r.T_m2c[:3, 3], R, t, mesh.vertices_m)
            rows.append({"case": name, "stride": s, "adds_m": e, "time_s": dt, "timings_s": r.timings_s})
            cells.append(f"{e * 100:.2f} / {dt:.1f}")
        print(f"| {name} | {len(space)} | " + " | ".join(cells) + " |", flush=True)
    for s in args.strides:
        errs = np.array([r["adds_m"] for r in rows if r["stride"] == s])
        tot = sum(r["time_s"] for r in rows if r["stride"] == s)
        print(
            f"stride {s}: mean ADD-S {errs.mean() * 100:.2f} cm, max {errs.max() * 100:.2f} cm, "
            f"< 2 cm {100 * (errs < 0.02).mean():.0f} %, total time {tot:.1f} s"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"device": args.device, "commit": commit, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
