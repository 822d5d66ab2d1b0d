"""`python -m perch_warp synth`: check the options, render the images in worker processes
(render.py) and write the BOP dataset, which appears only when complete."""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw
from tqdm import tqdm

from .. import bop
from ..errors import PerchError
from .models import available_ids, load_model
from .plan import (
    DEFAULT_SPP,
    DEFAULT_TARGETS,
    DEPTH_SCALE,
    IMAGE_ID_BASE,
    MAX_PATH_DEPTH,
    MITSUBA_VARIANT,
    SCENE_ID,
    YCBV_FOCAL_640,
    Config,
)
from .render import worker_init, worker_render


def write_preview(root: str | Path, path: str | Path | None = None, n: int = 8, columns: int = 4) -> Path:
    """A contact sheet of the first ``n`` images of a generated dataset, labelled with id, lighting, occlusion."""
    root = Path(root)
    scene = root / "test" / f"{SCENE_ID:06d}"
    cams = bop.read_json(scene / "scene_camera.json", "scene_camera.json")
    gts = bop.read_json(scene / "scene_gt.json", "scene_gt.json")
    tiles = []
    for im_id in sorted(cams, key=int)[:n]:
        im = Image.open(scene / "rgb" / f"{int(im_id):06d}.png").convert("RGB")
        if im.width > 320:
            im = im.resize((320, round(im.height * 320 / im.width)), Image.Resampling.LANCZOS)
        cam = cams[im_id]
        label = f"{im_id} {cam.get('lighting')} {cam.get('occlusion')} {[g['obj_id'] for g in gts[im_id]]}"
        draw = ImageDraw.Draw(im)
        draw.rectangle((0, 0, 7 * len(label), 12), fill=(0, 0, 0))
        draw.text((2, 0), label, fill=(255, 255, 0))
        tiles.append(im)
    cols = min(columns, len(tiles))
    rows = -(-len(tiles) // cols)
    w, h = tiles[0].size
    sheet = Image.new("RGB", (w * cols, h * rows))
    for k, im in enumerate(tiles):
        sheet.paste(im, ((k % cols) * w, (k // cols) * h))
    out = Path(path) if path is not None else root / "preview.png"
    sheet.save(out)
    return out


def generate(
    models_dir: str | Path,
    out_dir: str | Path,
    n_images: int,
    seed: int = 0,
    targets: tuple[int, ...] | list[int] = DEFAULT_TARGETS,
    distractors: list[int] | None = None,
    lighting: str = "mixed",
    occlusion: str = "mixed",
    width: int = 640,
    height: int = 480,
    focal: float | None = None,
    spp: int = DEFAULT_SPP,
    workers: int | None = None,
    max_objects: int = 5,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Render ``n_images`` tabletop images into a BOP dataset at ``out_dir``; returns a summary.

    ``distractors=None`` uses every other model in ``models_dir``. The dataset appears at
    ``out_dir`` only when complete (it is built in a temporary sibling folder).
    """
    models_dir = Path(models_dir)
    out_dir = Path(out_dir)
    if not models_dir.is_dir():
        raise PerchError(f"models directory not found: {models_dir}")
    _check_options(n_images, lighting, occlusion, width, height, spp, max_objects)
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise PerchError(f"output directory {out_dir} is not empty; pass --overwrite to replace it")
    targets, distractors = _check_ids(models_dir, targets, distractors)
    mitsuba_version = _mitsuba_version()

    models = {i: load_model(models_dir, i) for i in (*targets, *distractors)}
    K = camera_matrix(width, height, focal)
    n_workers = max(1, min(workers or os.cpu_count() or 1, n_images))
    # One single-threaded render per core also overlaps the ~2.5 s of serial per-image work
    # (textures, scene loading, PNGs) that a multi-threaded render leaves idle; a lone worker uses every core.
    threads = 1 if n_workers > 1 else (os.cpu_count() or 1)
    cfg = Config(
        models, targets, distractors, lighting, occlusion, width, height, K, spp, int(seed), max_objects, threads
    )

    results = _build_dataset(cfg, out_dir, n_images, n_workers, progress, models_dir, mitsuba_version)
    secs = [r["seconds"]["total"] for r in results]
    return {
        "out": str(out_dir),
        "images": n_images,
        "workers": n_workers,
        "seconds_per_image_mean": float(np.mean(secs)),
        "seconds_per_image_max": float(np.max(secs)),
    }


def _build_dataset(
    cfg: Config,
    out_dir: Path,
    n_images: int,
    n_workers: int,
    progress: bool,
    models_dir: Path,
    mitsuba_version: str,
) -> list[dict]:
    """Render the images and write the dataset in a temporary sibling of out_dir, moved into place once
    complete and removed on any failure; the images' results in image order."""
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        scene_dir = tmp / "test" / f"{SCENE_ID:06d}"
        for sub in ("rgb", "depth", "mask", "mask_visib"):
            (scene_dir / sub).mkdir(parents=True)
        jobs = [(i, str(scene_dir)) for i in range(n_images)]
        results = _run_jobs(cfg, jobs, n_workers, progress)
        results.sort(key=lambda r: r["im_id"])
        _write_dataset(tmp, cfg, results, models_dir, mitsuba_version)
        write_preview(tmp)
        _move_into_place(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return results


def _check_options(
    n_images: int, lighting: str, occlusion: str, width: int, height: int, spp: int, max_objects: int
) -> None:
    """Refuse options no image can be made with, naming the option."""
    if n_images < 1:
        raise PerchError(f"--scenes must be at least 1, got {n_images}")
    if lighting not in ("normal", "harsh", "mixed"):
        raise PerchError(f"--lighting must be normal, harsh or mixed, got {lighting!r}")
    if occlusion not in ("low", "high", "mixed"):
        raise PerchError(f"--occlusion must be low, high or mixed, got {occlusion!r}")
    if width < 16 or height < 16:
        raise PerchError(f"image size must be at least 16x16, got {width}x{height}")
    if spp < 1:
        raise PerchError(f"--spp must be at least 1, got {spp}")
    if not 1 <= max_objects <= 10:
        raise PerchError(f"--max-objects must be within 1..10, got {max_objects}")


def _check_ids(
    models_dir: Path, targets: tuple[int, ...] | list[int], distractors: list[int] | None
) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Target and distractor ids, each with a mesh in models_dir and in one role only; distractors
    None: every other mesh there."""
    found = available_ids(models_dir)
    if not found:
        raise PerchError(f"no BOP meshes (obj_NNNNNN.obj) in {models_dir}")
    targets = tuple(int(t) for t in targets)
    if not targets:
        raise PerchError("at least one target object id is needed (--objects)")
    for t in targets:
        if t not in found:
            raise PerchError(f"target object id {t} has no mesh obj_{t:06d}.obj in {models_dir}")
    if len(set(targets)) != len(targets):
        raise PerchError(f"--objects lists an id twice: {list(targets)}")
    if distractors is None:
        distractors = [i for i in found if i not in targets]
    for d in distractors:
        if d not in found:
            raise PerchError(f"distractor object id {d} has no mesh obj_{d:06d}.obj in {models_dir}")
        if d in targets:
            raise PerchError(f"object id {d} is both a target and a distractor")
    return targets, tuple(int(d) for d in distractors)


def _mitsuba_version() -> str:
    """Mitsuba's version; fails here, once, rather than in every worker when it is not installed."""
    try:
        # Optional (pip install perch_warp[synth]) and slow to import: only when generating.
        import mitsuba as mi
    except ImportError:
        raise PerchError("synth needs Mitsuba 3: pip install mitsuba") from None
    return mi.__version__


def camera_matrix(width: int, height: int, focal: float | None) -> np.ndarray:
    """Intrinsics K (pixels): YCB-Video's focal length and principal point scaled to the image size,
    or the given focal length (fx = fy)."""
    f = focal if focal is not None else YCBV_FOCAL_640 * width / 640.0
    cx = (312.9869 + 0.5) * width / 640.0 - 0.5
    cy = (241.3109 + 0.5) * height / 480.0 - 0.5
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def _write_dataset(root: Path, cfg: Config, results: list[dict], models_dir: Path, mitsuba_version: str) -> None:
    """The BOP files of the rendered images (results sorted by im_id) under root: the scene's JSON
    files, camera.json, the BOP 19 targets and dataset_info.json (millimetres)."""
    scene_dir = root / "test" / f"{SCENE_ID:06d}"
    bop.write_scene(
        scene_dir,
        {r["im_id"]: r["camera"] for r in results},
        {r["im_id"]: r["gt"] for r in results},
        {r["im_id"]: r["info"] for r in results},
    )
    K, w, h = cfg.K, cfg.width, cfg.height
    bop.write_json(
        root / "camera.json",
        {
            "cx": K[0, 2],
            "cy": K[1, 2],
            "fx": K[0, 0],
            "fy": K[1, 1],
            "width": w,
            "height": h,
            "depth_scale": DEPTH_SCALE,
        },
    )
    bop.write_json(
        root / "test_targets_bop19.json",
        [
            {"im_id": r["im_id"], "inst_count": 1, "obj_id": g["obj_id"], "scene_id": SCENE_ID}
            for r in results
            for g in r["gt"]
            if g["obj_id"] in cfg.targets
        ],
    )
    info = {
        "generator": "perch_warp.synth",
        "renderer": f"mitsuba {mitsuba_version} {MITSUBA_VARIANT}",
        "models_dir": str(models_dir.resolve()),
        "split": "test",
        "scene_ids": [SCENE_ID],
        "image_id_base": IMAGE_ID_BASE,
        "n_images": len(results),
        "seed": cfg.seed,
        "targets": list(cfg.targets),
        "distractors": list(cfg.distractors),
        "lighting": cfg.lighting,
        "occlusion": cfg.occlusion,
        "width": w,
        "height": h,
        "cam_K": K.reshape(-1).tolist(),
        "spp": cfg.spp,
        "max_path_depth": MAX_PATH_DEPTH,
        "depth_scale": DEPTH_SCALE,
        "units": "mm",
        "labels": "scene_camera.json entries carry 'lighting' (normal|harsh) and 'occlusion' (low|high)",
    }
    bop.write_json(root / "dataset_info.json", info)


def _move_into_place(tmp: Path, out_dir: Path) -> None:
    """The finished dataset at out_dir, replacing what was there (--overwrite) only now."""
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
        out_dir.rename(old / "d")
        tmp.rename(out_dir)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(out_dir)


def _run_jobs(cfg: Config, jobs: list[tuple[int, str]], n_workers: int, progress: bool) -> list[dict]:
    bar = tqdm(total=len(jobs), desc="synth", unit="img", disable=not progress)
    results = []
    try:
        if n_workers == 1:
            worker_init(cfg)
            for job in jobs:
                results.append(worker_render(job))
                bar.update()
        else:
            # spawn: Mitsuba/Dr.Jit keep thread pools that do not survive fork.
            with mp.get_context("spawn").Pool(n_workers, initializer=worker_init, initargs=(cfg,)) as pool:
                for r in pool.imap_unordered(worker_render, jobs):
                    results.append(r)
                    bar.update()
    finally:
        bar.close()
    return results


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", required=True, help="BOP models folder with obj_NNNNNN.obj (+ .mtl/.png), mm")
    parser.add_argument("--out", required=True, help="dataset folder to create (BOP layout, see docs/synthetic.md)")
    parser.add_argument("--scenes", type=int, required=True, help="number of images (each its own arrangement)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--objects",
        type=int,
        nargs="+",
        default=list(DEFAULT_TARGETS),
        help="target object ids, at least one per image (default 3 4 8 9)",
    )
    parser.add_argument(
        "--distractors",
        type=int,
        nargs="*",
        default=None,
        help="distractor ids (default: every other model; give none for no distractors)",
    )
    parser.add_argument("--lighting", choices=("normal", "harsh", "mixed"), default="mixed")
    parser.add_argument("--occlusion", choices=("low", "high", "mixed"), default="mixed")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument(
        "--focal",
        type=float,
        default=None,
        help="focal length in pixels, fx = fy (default YCB-Video's 1066.8, scaled to --width)",
    )
    parser.add_argument("--spp", type=int, default=DEFAULT_SPP, help=f"samples per pixel (default {DEFAULT_SPP})")
    parser.add_argument("--max-objects", type=int, default=5, help="objects per image at most (default 5)")
    parser.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    summary = generate(
        args.models,
        args.out,
        args.scenes,
        seed=args.seed,
        targets=args.objects,
        distractors=args.distractors,
        lighting=args.lighting,
        occlusion=args.occlusion,
        width=args.width,
        height=args.height,
        focal=args.focal,
        spp=args.spp,
        workers=args.workers,
        max_objects=args.max_objects,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    print(
        f"wrote {summary['images']} images to {summary['out']} in {time.perf_counter() - t0:.1f} s "
        f"({summary['workers']} workers, {summary['seconds_per_image_mean']:.1f} s per image per worker)"
    )
    return 0
