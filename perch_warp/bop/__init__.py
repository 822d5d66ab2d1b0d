"""BOP datasets: every read and write of BOP files and the targets they hold (cf. bop_toolkit_lib's `inout`).

inout   -- the files: scene_camera.json, scene_gt(_info).json, models_info.json, camera files, depth PNGs,
           results.csv, and the writers of the scenes that `demo` and `synth` make.
tables  -- an image's table frame: cam_R_w2c/cam_t_w2c, else a RANSAC plane fit to its depth image.
targets -- the ground-truth instances to find (`select_targets`), with each image's camera.

All BOP files carry millimetres; everything returned is in metres except where a name ends in `_mm`.
"""

from .inout import (
    GT_ROTATION_TOLERANCE,
    IMAGE_SUFFIXES,
    MESH_SUFFIXES,
    RESULTS_HEADER,
    BopResult,
    Dataset,
    GtInstance,
    camera_for_image,
    gt_rotation,
    image_path,
    image_size,
    load_models_info,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    open_dataset,
    read_camera_json,
    read_depth_mm,
    read_json,
    read_results,
    truth_instance,
    write_json,
    write_results,
    write_scene,
)
from .tables import (
    depth_points_m,
    fit_plane_ransac,
    table_for_image,
    table_from_depth,
    table_from_plane,
    table_source_for,
)
from .targets import (
    IMAGE_LABEL_KEYS,
    ImageInfo,
    Selection,
    TableCache,
    Target,
    image_labels,
    select_targets,
)

__all__ = [
    "BopResult",
    "camera_for_image",
    "Dataset",
    "depth_points_m",
    "fit_plane_ransac",
    "gt_rotation",
    "GT_ROTATION_TOLERANCE",
    "GtInstance",
    "IMAGE_LABEL_KEYS",
    "image_labels",
    "image_path",
    "image_size",
    "IMAGE_SUFFIXES",
    "ImageInfo",
    "load_models_info",
    "load_scene_camera",
    "load_scene_gt",
    "load_scene_gt_info",
    "MESH_SUFFIXES",
    "open_dataset",
    "read_camera_json",
    "read_depth_mm",
    "read_json",
    "read_results",
    "RESULTS_HEADER",
    "select_targets",
    "Selection",
    "table_for_image",
    "table_from_depth",
    "table_from_plane",
    "table_source_for",
    "TableCache",
    "Target",
    "truth_instance",
    "write_json",
    "write_results",
    "write_scene",
]
