"""Evaluation targets of a BOP dataset: every ground-truth instance of the selected objects in the
selected images, with each image's camera and table frame checked before any search."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import PerchError
from ..table import Table
from .inout import Dataset, camera_for_image, image_path, load_scene_camera, load_scene_gt, load_scene_gt_info
from .tables import table_for_image, table_source_for

# Per-image labels read from scene_camera.json entries (our synthetic generator writes them;
# BOP readers ignore unknown keys, and real BOP datasets have none, so nothing changes there).
IMAGE_LABEL_KEYS = ("lighting", "occlusion")


@dataclass(frozen=True)
class Target:
    """One ground-truth instance to find. `inst` is its index in the image's scene_gt.json list."""

    scene_id: int
    im_id: int
    inst: int
    obj_id: int
    R_gt: np.ndarray  # model -> camera
    t_gt_m: np.ndarray  # metres
    visib_fract: float | None = None
    labels: dict[str, str] = field(default_factory=dict)  # IMAGE_LABEL_KEYS found in the image's entry
    gt_projected: bool = False  # R_gt was near-orthonormal in the file and projected onto SO(3)
    problem: str | None = None  # why the target cannot be evaluated (recorded as failed, the run goes on)

    @property
    def key(self) -> tuple[int, int, int]:
        return (self.scene_id, self.im_id, self.inst)


@dataclass
class ImageInfo:
    scene_id: int
    im_id: int
    rgb: Path
    camera: Camera
    entry: dict  # raw scene_camera.json entry
    camera_file: Path
    targets: list[Target] = field(default_factory=list)


@dataclass
class Selection:
    images: list[ImageInfo]
    skipped_no_model: Counter  # obj_id -> instances skipped because the mesh is absent
    model_paths: dict[int, Path]

    @property
    def targets(self) -> list[Target]:
        return [t for im in self.images for t in im.targets]


def image_labels(entry: dict) -> dict[str, str]:
    """The string-valued IMAGE_LABEL_KEYS of a scene_camera.json entry (other keys and values are not labels)."""
    return {k: entry[k] for k in IMAGE_LABEL_KEYS if isinstance(entry.get(k), str)}


def select_targets(
    ds: Dataset,
    scenes: Sequence[int] | None = None,
    objects: Sequence[int] | None = None,
    max_images: int | None = None,
    table_source: str = "auto",
) -> Selection:
    """Every instance of the selected objects in the selected scenes, images in (scene, image) order.

    An instance whose model has no mesh is skipped and counted, unless the object was
    asked for by `objects` or is listed in models_info.json: then the missing mesh is
    an error naming the expected file. `max_images` keeps the first N images that have
    a target. Cameras (image size against cam_K) and the availability of a table frame
    are checked here, before any search, so a bad dataset fails at once.
    """
    wanted = set(objects) if objects else None
    all_scenes = _selected_scenes(ds, scenes)
    model_paths = _asked_models(ds, wanted)
    images: list[ImageInfo] = []
    skipped: Counter = Counter()
    for scene_id in all_scenes:
        room = None if max_images is None else max_images - len(images)
        images += _scene_images(ds, scene_id, wanted, model_paths, skipped, table_source, room)
    return Selection(images, skipped, model_paths)


def _selected_scenes(ds: Dataset, scenes: Sequence[int] | None) -> list[int]:
    """The dataset's scene ids, only those in `scenes` if given (each of which must exist)."""
    all_scenes = ds.scene_ids()
    if scenes:
        missing = sorted(set(scenes) - set(all_scenes))
        if missing:
            raise PerchError(f"scene(s) {missing} not found in {ds.split_dir} (has {all_scenes[:20]})")
        all_scenes = [s for s in all_scenes if s in set(scenes)]
    return all_scenes


def _asked_models(ds: Dataset, wanted: set[int] | None) -> dict[int, Path]:
    """The mesh of every object asked for; a missing one is an error naming the expected file."""
    model_paths: dict[int, Path] = {}
    for obj_id in sorted(wanted or ()):
        p = ds.model_path(obj_id)
        if p is None:
            expected = ds.models_dir / f"obj_{obj_id:06d}.obj"
            raise PerchError(f"no mesh for object {obj_id}: expected {expected} (or .ply)")
        model_paths[obj_id] = p
    return model_paths


def _scene_images(
    ds: Dataset,
    scene_id: int,
    wanted: set[int] | None,
    model_paths: dict[int, Path],
    skipped: Counter,
    table_source: str,
    room: int | None,
) -> list[ImageInfo]:
    """The scene's images that have a target (at most `room` of them, when given), in image order,
    each checked (camera, image file, table frame); instances without a mesh are counted in `skipped`."""
    sdir = ds.scene_dir(scene_id)
    gt_file, cam_file, info_file = sdir / "scene_gt.json", sdir / "scene_camera.json", sdir / "scene_gt_info.json"
    gts = load_scene_gt(gt_file)
    cams = load_scene_camera(cam_file)
    infos = load_scene_gt_info(info_file) if info_file.exists() else None
    images: list[ImageInfo] = []
    for im_id in sorted(gts):
        if room is not None and len(images) >= room:
            break
        targets = []
        # A missing entry is an error below, once the image is known to have targets.
        labels = image_labels(cams.get(im_id, {}))
        for k, g in enumerate(gts[im_id]):
            if wanted is not None and g.obj_id not in wanted:
                continue
            if not _has_mesh(ds, g.obj_id, model_paths):
                skipped[g.obj_id] += 1
                continue
            vf = _visib_fract(infos, im_id, k, len(gts[im_id]), info_file, gt_file)
            targets.append(
                Target(scene_id, im_id, k, g.obj_id, g.R_m2c, g.t_m2c_m, vf, dict(labels), g.projected, g.problem)
            )
        if targets:
            images.append(_checked_image(ds, sdir, scene_id, im_id, cams, cam_file, gt_file, table_source, targets))
    return images


def _checked_image(
    ds: Dataset,
    sdir: Path,
    scene_id: int,
    im_id: int,
    cams: dict,
    cam_file: Path,
    gt_file: Path,
    table_source: str,
    targets: list[Target],
) -> ImageInfo:
    """An image that has targets, with its camera entry, photo and table frame checked before any search."""
    if im_id not in cams:
        raise PerchError(f"{cam_file} has no entry for image {im_id} (listed in {gt_file})")
    rgb = image_path(sdir, im_id, "rgb")
    if rgb is None:
        raise PerchError(f"image not found: {sdir / 'rgb' / f'{im_id:06d}.png'} (listed in {gt_file})")
    entry = cams[im_id]
    camera = camera_for_image(ds, entry, rgb, im_id, cam_file)
    table_source_for(entry, sdir, im_id, cam_file, table_source)  # fail before any search
    return ImageInfo(scene_id, im_id, rgb, camera, entry, cam_file, targets)


def _has_mesh(ds: Dataset, obj_id: int, model_paths: dict[int, Path]) -> bool:
    """Whether the object has a mesh (recorded in model_paths); a mesh missing for an object that
    models_info.json lists is an error naming the file."""
    if obj_id in model_paths:
        return True
    p = ds.model_path(obj_id)
    if p is None:
        if obj_id in ds.models_info:
            raise PerchError(
                f"{ds.models_dir / 'models_info.json'} lists object {obj_id} but its mesh "
                f"{ds.models_dir / f'obj_{obj_id:06d}.obj'} (or .ply) is missing"
            )
        return False
    model_paths[obj_id] = p
    return True


def _visib_fract(infos: dict | None, im_id: int, k: int, n: int, info_file: Path, gt_file: Path) -> float | None:
    """Instance k's visib_fract from scene_gt_info.json (None without the file or the key)."""
    if infos is None:
        return None
    lst = infos.get(im_id)
    if lst is None or len(lst) != n:
        raise PerchError(f"{info_file}: image {im_id} must list one entry per instance of {gt_file}")
    return float(lst[k]["visib_fract"]) if "visib_fract" in lst[k] else None


@dataclass
class TableCache:
    """Table frames per image (the depth fit costs ~50 ms; the errors need them again after the search)."""

    how: str = "auto"
    tables: dict = field(default_factory=dict)

    def get(self, im: ImageInfo) -> tuple[Table, str]:
        key = (im.scene_id, im.im_id)
        if key not in self.tables:
            self.tables[key] = table_for_image(
                im.entry, im.rgb.parent.parent, im.im_id, im.camera, im.camera_file, self.how
            )
        return self.tables[key]
