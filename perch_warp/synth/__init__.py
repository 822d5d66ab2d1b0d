"""Photorealistic synthetic tabletop test scenes in BOP format, rendered with Mitsuba 3.

The images come from Mitsuba 3's path tracer (variant ``scalar_rgb``), a physically
based renderer that shares no code with the engine's own renderer, so a pose search
tested on them cannot profit from matching its own rendering model.

Every image is its own tabletop arrangement: 1-5 objects (at least one target) stand
upright in their resting pose (model +z along the table normal, lowest vertex on the
table top) at random x, y and yaw with non-intersecting footprints, seen by a camera
at a random distance, elevation, azimuth and slight roll. Scenes have a procedural
table (wood, laminate or cloth) on legs, a floor, a wall, a procedural indoor
environment map, and either soft lighting (large area light plus windows in the
environment, label ``normal``) or hard lighting (a spot light and a dim environment,
label ``harsh``). A camera-like post-process adds auto exposure, vignetting, shot and
read noise.

Output layout (``--out DIR``), BOP "test" split with all images in one scene folder::

    DIR/dataset_info.json            generator settings; "models_dir" = absolute path of the meshes used
    DIR/preview.png                  contact sheet of the first 8 images
    DIR/camera.json                  BOP camera file (intrinsics, depth_scale)
    DIR/test_targets_bop19.json      the target instances (BOP 19 format)
    DIR/test/000001/rgb/{im_id:06d}.png
    DIR/test/000001/depth/{im_id:06d}.png                 uint16, depth_scale 0.1 (mm = value * 0.1)
    DIR/test/000001/mask/{im_id:06d}_{gt_id:06d}.png      full silhouette of each instance
    DIR/test/000001/mask_visib/{im_id:06d}_{gt_id:06d}.png  its visible part
    DIR/test/000001/scene_camera.json
    DIR/test/000001/scene_gt.json
    DIR/test/000001/scene_gt_info.json

Image ids start at 1 (as in YCB-Video's BOP test split). ``scene_camera.json`` entries
hold ``cam_K`` (row-major), ``depth_scale``, the table frame ``cam_R_w2c``/``cam_t_w2c``
(mm; world z = table normal, z = 0 the table top) and two extra keys that BOP readers
ignore: ``"lighting": "normal"|"harsh"`` and ``"occlusion": "low"|"high"``.
``scene_gt_info.json`` counts pixels from Mitsuba-rendered masks (pixel-centre rays):
the full mask of an instance is a render of that object alone, the visible mask keeps
the pixels where that object is the nearest object surface.

The generator is deterministic for a seed: image ``i`` draws everything from an RNG
seeded with ``(seed, i)``, so results do not depend on the number of worker processes.
"""

# The names tests, tools and the CLI use, from the modules that define them.
from .command import add_arguments, generate, run, write_preview
from .models import ModelSpec, available_ids, load_model, read_obj_vertices
from .plan import DEFAULT_SPP, DEFAULT_TARGETS, DEPTH_SCALE, Config, ImagePlan, plan_image
from .render import render_image

__all__ = [
    "DEFAULT_SPP",
    "DEFAULT_TARGETS",
    "DEPTH_SCALE",
    "Config",
    "ImagePlan",
    "ModelSpec",
    "add_arguments",
    "available_ids",
    "generate",
    "load_model",
    "plan_image",
    "read_obj_vertices",
    "render_image",
    "run",
    "write_preview",
]
