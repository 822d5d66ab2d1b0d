"""The bench workload and the fixtures tools/ share: one BOP frame, its table, an object instance and
its search region (table frame, metres), the search camera and poses of its grid (model to camera)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import bop, pose_error
from ..camera import Camera
from ..errors import PerchError
from ..image import load_rgb
from ..mesh import ObjectMesh, load_mesh
from ..paths import shared_file
from ..render import project_boxes
from ..search_space import SearchSpace
from ..table import RestingPose, Table, decompose_on_table, model_to_camera


@dataclass
class Workload:
    """One frame, one object instance and its search region (table frame, metres)."""

    label: str
    image: np.ndarray  # uint8 (H, W, 3), full size
    camera: Camera  # full-size intrinsics
    table: Table
    table_source: str
    mesh: ObjectMesh
    resting: RestingPose  # height, roll, pitch from the ground truth (thesis protocol)
    R_gt: np.ndarray  # model -> camera
    t_gt_m: np.ndarray
    truth_xy_yaw: tuple[float, float, float]  # table frame: metres, metres, radians
    space: SearchSpace
    adds_points_m: np.ndarray  # model points for ADD-S, subsampled as `perch_warp eval` does


def default_dataset() -> Path | None:
    """shared/data/ycbv when the shared folder is found (see perch_warp.paths)."""
    return shared_file("data", "ycbv")


def load_workload(
    dataset: str | Path,
    scene_id: int,
    im_id: int,
    obj_id: int,
    clip_m: float,
    xy_step_m: float,
    yaw_step_rad: float,
    split: str = "test",
) -> Workload:
    """The frame, its table, the object's first instance and the visible-table region, as `perch_warp eval` has them."""
    for name, v, unit in (("--clip", clip_m, "m"), ("--xy-step", xy_step_m, "m"), ("--yaw-step", yaw_step_rad, "rad")):
        if not (math.isfinite(v) and v > 0):
            raise PerchError(f"{name} must be a positive number of {unit}, got {v}")
    ds = bop.open_dataset(dataset, split)
    selection = bop.select_targets(ds, scenes=[scene_id], objects=[obj_id])
    im = next((i for i in selection.images if i.im_id == im_id), None)
    if im is None:
        raise PerchError(f"object {obj_id} is not in scene {scene_id} image {im_id} of {ds.split_dir}")
    target = im.targets[0]  # the first instance, as listed in scene_gt.json
    table, how = bop.TableCache(how="auto").get(im)
    resting, gx, gy, gyaw = decompose_on_table(table, target.R_gt, target.t_gt_m)
    # The default region of `perch_warp eval`: the visible table, clipped (never the ground truth).
    space = SearchSpace.visible_table(im.camera, table, xy_step_m=xy_step_m, yaw_step_rad=yaw_step_rad, clip_m=clip_m)
    len(space)  # validates the ranges
    mesh = load_mesh(selection.model_paths[obj_id])
    return Workload(
        label=f"{ds.root.name} {split} scene {scene_id} image {im_id}, {ds.object_name(obj_id)} (obj {obj_id})",
        image=load_rgb(im.rgb),
        camera=im.camera,
        table=table,
        table_source=how,
        mesh=mesh,
        resting=resting,
        R_gt=target.R_gt,
        t_gt_m=target.t_gt_m,
        truth_xy_yaw=(gx, gy, gyaw),
        space=space,
        adds_points_m=pose_error.subsample_points(mesh.vertices_m),
    )


def search_camera(camera: Camera, image_scale: float) -> Camera:
    """The camera the engine searches with (the photo resized by `image_scale`)."""
    return camera if image_scale == 1.0 else camera.scaled(image_scale)


def sample_grid_poses(
    w: Workload, n: int, seed: int, boxes_of: Callable[[np.ndarray, np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to n poses of the workload's grid drawn at random (`seed`), those with an empty image box
    left out: R_m2c (m, 3, 3), t_m2c_m (m, 3) metres (model to camera) and their pixel boxes (m, 4)
    (x0, y0, w, h) from boxes_of(R_m2c, t_m2c_m). The poses tools/ time kernels on."""
    R, t = model_to_camera(w.table, w.resting, *w.space.sample(n, seed))
    boxes = boxes_of(R, t)
    keep = (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
    return R[keep], t[keep], boxes[keep]


def poses_in_view(
    w: Workload, camera: Camera, n: int, max_tried: int = 4096
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n poses of the search grid whose whole projection lies in the image, drawn with a fixed seed.

    Returns (R_m2c (n, 3, 3), t_m2c_m (n, 3), (x_m, y_m, yaw_rad) (n, 3)). At most
    `max_tried` grid poses are projected, so this stays cheap for large grids. Drawn at
    random (seed 0) rather than evenly spaced: with yaw varying fastest, an even spacing
    can alias onto one yaw.
    """
    if n < 1:
        raise PerchError(f"--ray-poses must be at least 1, got {n}")
    rng = np.random.default_rng(0)
    x, y, yaw = w.space.candidates()
    pick = np.sort(rng.choice(len(x), size=min(len(x), max_tried), replace=False))
    R, t = model_to_camera(w.table, w.resting, x[pick], y[pick], yaw[pick])
    box = project_boxes(camera, w.mesh.hull_points_m(), R, t)
    inside = (
        (box[:, 2] > 0)
        & (box[:, 0] >= 0)
        & (box[:, 1] >= 0)
        & (box[:, 0] + box[:, 2] <= camera.width)
        & (box[:, 1] + box[:, 3] <= camera.height)
    )
    ok = np.flatnonzero(inside)
    if len(ok) == 0:
        raise PerchError(f"no pose of the search grid lies wholly in the image ({w.space.describe()})")
    sel = np.sort(rng.choice(ok, size=min(n, len(ok)), replace=False))
    return R[sel], t[sel], np.stack([x[pick][sel], y[pick][sel], yaw[pick][sel]], -1)


def add_frame_arguments(parser) -> None:
    """--dataset/--scene/--image/--obj: the reference frame and object, shared with tools/."""
    parser.add_argument("--dataset", type=Path, default=None, help="BOP dataset folder (default: shared/data/ycbv)")
    parser.add_argument("--scene", type=int, default=2, help="scene id (default: 2)")
    parser.add_argument("--image", type=int, default=1, help="image id (default: 1)")
    parser.add_argument("--obj", type=int, default=9, help="object id; its first instance in the image (default: 9)")


def add_pose_sample_arguments(parser) -> None:
    """--poses/--seed: the random grid poses of sample_grid_poses, shared with tools/."""
    parser.add_argument("--poses", type=int, default=300, help="random poses of the reference grid (default 300)")
    parser.add_argument("--seed", type=int, default=0)
