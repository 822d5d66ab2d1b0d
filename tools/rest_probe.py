"""How well does each stable resting pose of a mesh explain a real frame near its ground truth? (issue 19)

    python tools/rest_probe.py --dataset ../shared/data/ycbv --scene 2 --obj-id 3 [--image-scale 0.5]

For one ground-truth instance: Engine.score on a grid around the truth's table position (x, y within
--radius at --xy-step, every yaw at --yaw-step), under the ground truth's own resting pose and under each
of the mesh's stable poses (perch_warp.resting.stable_rests); prints each pose's best score there, its
height (model origin above the table top, metres) and its tilt from the truth's rotation. A diagnostic
that reads the ground truth: never a search setting. Exit 1 on bad input.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from perch_warp.bop import open_dataset, read_camera_json, truth_instance
from perch_warp.bop.inout import image_path
from perch_warp.camera import camera_from_entry
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.features import load_feature_weights
from perch_warp.image import load_rgb
from perch_warp.mesh import load_mesh
from perch_warp.resting import stable_rests
from perch_warp.table import Table, decompose_on_table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", required=True, help="BOP dataset folder (models/, test/SCENE/...)")
    ap.add_argument("--scene", type=int, required=True)
    ap.add_argument("--image", type=int, default=1, help="image id (default: 1)")
    ap.add_argument("--obj-id", type=int, required=True)
    ap.add_argument("--weights", default="caffe")
    ap.add_argument("--image-scale", type=float, default=0.5)
    ap.add_argument("--radius", type=float, default=0.02, help="x, y half-width around the truth, m (0.02)")
    ap.add_argument("--xy-step", type=float, default=0.005, help="m (0.005)")
    ap.add_argument("--yaw-step", type=float, default=5.0, help="deg (5)")
    args = ap.parse_args(argv)
    try:
        report(args)
    except PerchError as e:
        print(f"rest_probe: {e}", file=sys.stderr)
        return 1
    return 0


def report(args: argparse.Namespace) -> None:
    ds = open_dataset(args.dataset)
    scene = ds.scene_dir(args.scene)
    rgb = image_path(scene, args.image)
    if rgb is None:
        raise PerchError(f"no image {args.image} in {scene / 'rgb'}")
    if ds.model_path(args.obj_id) is None:
        raise PerchError(f"no mesh for object {args.obj_id} in {ds.models_dir}")
    image = load_rgb(rgb)
    entry = read_camera_json(scene / "scene_camera.json", args.image)
    camera = camera_from_entry(entry, image.shape[1], image.shape[0], source=str(scene / "scene_camera.json"))
    table = Table.from_entry(entry)  # table -> camera, metres
    gt = truth_instance(scene / "scene_gt.json", args.image, args.obj_id)
    rest_gt, gx, gy, gyaw = decompose_on_table(table, gt.R_m2c, gt.t_m2c_m)
    mesh = load_mesh(ds.model_path(args.obj_id))
    config = EngineConfig(image_scale=args.image_scale)
    engine = Engine(mesh, load_feature_weights(args.weights), "cpu", config)
    d = np.arange(-args.radius, args.radius + 1e-9, args.xy_step)
    yaws = np.radians(np.arange(-180.0, 180.0, args.yaw_step))
    x, y, yaw = (a.ravel() for a in np.meshgrid(gx + d, gy + d, gyaw + yaws, indexing="ij"))

    def best(resting) -> float:
        return float(engine.score(image, camera, table, resting, x, y, yaw).max())

    print(
        f"scene {args.scene} image {args.image} obj {args.obj_id}: {len(x)} poses within {args.radius} m of the truth"
    )
    print(f"  ground truth's resting pose   height {rest_gt.z_m:.4f} m                best {best(rest_gt):.4f}")
    for r in stable_rests(mesh.vertices_m, mesh.faces):
        rel = rest_gt.R_rest @ r.pose.R_rest.T  # the truth's rest relative to this one; tilt: its z axis from +z
        tilt = math.degrees(math.acos(float(np.clip(rel[2, 2], -1.0, 1.0))))
        print(f"  {r.label:30s} height {r.pose.z_m:.4f} m  tilt {tilt:5.1f} deg  best {best(r.pose):.4f}")


if __name__ == "__main__":
    sys.exit(main())
