"""Synthetic BOP scenes (perch_warp.synth): annotations agree with Mitsuba's rendered masks.

Tiny sets (160x120, a few samples per pixel) keep this fast; the checks are geometric,
so image quality does not matter here.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from perch_warp import synth
from perch_warp.errors import PerchError

REPO = Path(__file__).resolve().parents[1]


def _shared() -> Path:
    return Path(os.environ.get("PERCH_WARP_SHARED", REPO.parent / "shared"))


YCBV_MODELS = _shared() / "data" / "ycbv" / "models"

needs_mitsuba = pytest.mark.skipif(
    __import__("importlib").util.find_spec("mitsuba") is None, reason="mitsuba not installed (pip install mitsuba)"
)
needs_ycbv = pytest.mark.skipif(
    not (YCBV_MODELS / "obj_000003.obj").is_file(), reason=f"YCB-Video models not found at {YCBV_MODELS}"
)


def _write_box(path: Path, size: tuple[float, float, float], z0: float) -> None:
    """A closed box mesh in mm, bottom at z = z0 (not 0, so resting needs a lift), no texture."""
    sx, sy, sz = size
    v = np.array([[x, y, z] for x in (-sx / 2, sx / 2) for y in (-sy / 2, sy / 2) for z in (z0, z0 + sz)])
    faces = [
        (0, 2, 3),
        (0, 3, 1),
        (4, 5, 7),
        (4, 7, 6),
        (0, 1, 5),
        (0, 5, 4),
        (2, 6, 7),
        (2, 7, 3),
        (0, 4, 6),
        (0, 6, 2),
        (1, 3, 7),
        (1, 7, 5),
    ]
    lines = [f"v {a:.3f} {b:.3f} {c:.3f}" for a, b, c in v] + [f"f {i + 1} {j + 1} {k + 1}" for i, j, k in faces]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def box_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("box_models")
    _write_box(d / "obj_000001.obj", (60.0, 40.0, 110.0), -55.0)
    _write_box(d / "obj_000002.obj", (80.0, 80.0, 40.0), -10.0)
    _write_box(d / "obj_000003.obj", (50.0, 90.0, 70.0), 0.0)
    return d


def _generate(models: Path, out: Path, **kw) -> Path:
    args = dict(width=160, height=120, spp=4, progress=False, seed=7)
    args.update(kw)
    synth.generate(models, out, **args)
    return out


def _surface_points(obj_path: Path, n: int = 3000, seed: int = 0) -> np.ndarray:
    """Random points on the mesh surface (mm): every one projects inside the object's silhouette."""
    v, f = [], []
    for line in obj_path.read_text().splitlines():
        if line.startswith("v "):
            v.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            f.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:4]])
    v, f = np.asarray(v), np.asarray(f)
    rng = np.random.default_rng(seed)
    tri = v[f[rng.integers(len(f), size=n)]]
    a, b = rng.random((2, n, 1))
    flip = (a + b) > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    return np.vstack([v, tri[:, 0] + a * (tri[:, 1] - tri[:, 0]) + b * (tri[:, 2] - tri[:, 0])])


def _check_dataset(root: Path, models: Path) -> None:
    from PIL import Image
    from scipy.ndimage import binary_dilation

    scene = root / "test" / "000001"
    cams = json.loads((scene / "scene_camera.json").read_text())
    gts = json.loads((scene / "scene_gt.json").read_text())
    infos = json.loads((scene / "scene_gt_info.json").read_text())
    info = json.loads((root / "dataset_info.json").read_text())
    assert info["models_dir"] == str(models.resolve())
    assert sorted(cams) == sorted(gts) == sorted(infos)
    for im_id, cam in cams.items():
        assert cam["lighting"] in ("normal", "harsh") and cam["occlusion"] in ("low", "high")
        K = np.asarray(cam["cam_K"]).reshape(3, 3)
        R_w2c = np.asarray(cam["cam_R_w2c"]).reshape(3, 3)
        t_w2c = np.asarray(cam["cam_t_w2c"])
        rgb = np.asarray(Image.open(scene / "rgb" / f"{int(im_id):06d}.png"))
        assert rgb.shape == (info["height"], info["width"], 3)
        assert 1 <= len(gts[im_id]) <= 5
        for gt_id, (gt, gi) in enumerate(zip(gts[im_id], infos[im_id], strict=True)):
            mask = np.asarray(Image.open(scene / "mask" / f"{int(im_id):06d}_{gt_id:06d}.png")) > 0
            visib = np.asarray(Image.open(scene / "mask_visib" / f"{int(im_id):06d}_{gt_id:06d}.png")) > 0
            assert gi["px_count_all"] == mask.sum() > 0
            assert gi["px_count_visib"] == visib.sum() and not np.any(visib & ~mask)
            assert gi["visib_fract"] == pytest.approx(visib.sum() / mask.sum())

            R = np.asarray(gt["cam_R_m2c"]).reshape(3, 3)
            t = np.asarray(gt["cam_t_m2c"])
            pts = _surface_points(models / f"obj_{gt['obj_id']:06d}.obj")
            pc = pts @ R.T + t
            uv = np.round(pc[:, :2] / pc[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]).astype(int)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < mask.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < mask.shape[0])
            assert inside.all(), f"image {im_id} object {gt['obj_id']}: annotation projects outside the image"
            # One pixel of slack: a silhouette vertex may round to the pixel just outside the mask.
            on_mask = binary_dilation(mask)[uv[:, 1], uv[:, 0]]
            assert on_mask.mean() >= 0.97, f"image {im_id} object {gt['obj_id']}: {on_mask.mean():.3f} on mask"
            # And the other way: the projection spans the rendered silhouette (catches scale errors).
            x, y, w, h = gi["bbox_obj"]
            assert abs(uv[:, 0].min() - x) <= 1 and abs(uv[:, 0].max() - (x + w - 1)) <= 1
            assert abs(uv[:, 1].min() - y) <= 1 and abs(uv[:, 1].max() - (y + h - 1)) <= 1

            # Resting on the table: model -> world, lowest point at z = 0, model +z along the normal.
            R_m2w = R_w2c.T @ R
            pw = (pc - t_w2c) @ R_w2c  # R_w2c^T (X_c - t_w2c)
            assert abs(pw[:, 2].min()) < 1.0, f"image {im_id} object {gt['obj_id']} lowest point z={pw[:, 2].min()}"
            assert R_m2w[2, 2] == pytest.approx(1.0, abs=1e-6)


@needs_mitsuba
@needs_ycbv
def test_ycbv_annotations_match_rendered_masks(tmp_path: Path) -> None:
    out = _generate(YCBV_MODELS, tmp_path / "ds", n_images=2, workers=1, lighting="mixed", occlusion="mixed")
    _check_dataset(out, YCBV_MODELS)
    targets = json.loads((out / "test_targets_bop19.json").read_text())
    gts = json.loads((out / "test" / "000001" / "scene_gt.json").read_text())
    for im_id, gt in gts.items():
        assert any(g["obj_id"] in synth.DEFAULT_TARGETS for g in gt), f"image {im_id} has no target"
    assert {t["obj_id"] for t in targets} <= set(synth.DEFAULT_TARGETS)


@needs_mitsuba
def test_boxes_deterministic_across_worker_counts(tmp_path: Path, box_models: Path) -> None:
    a = _generate(box_models, tmp_path / "a", n_images=2, targets=[1], workers=1, occlusion="high")
    b = _generate(box_models, tmp_path / "b", n_images=2, targets=[1], workers=2, occlusion="high")
    _check_dataset(a, box_models)
    names = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file())
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), f"{name} differs between runs"
    c = _generate(box_models, tmp_path / "c", n_images=1, targets=[1], workers=1, occlusion="high", seed=8)
    assert (c / "test/000001/scene_gt.json").read_bytes() != (a / "test/000001/scene_gt.json").read_bytes()


def test_bad_input(tmp_path: Path, box_models: Path) -> None:
    with pytest.raises(PerchError, match="obj_000042.obj"):
        synth.generate(box_models, tmp_path / "x", 1, targets=[42], progress=False)
    with pytest.raises(PerchError, match="models directory not found"):
        synth.generate(tmp_path / "nope", tmp_path / "x", 1, progress=False)
    with pytest.raises(PerchError, match="both a target and a distractor"):
        synth.generate(box_models, tmp_path / "x", 1, targets=[1], distractors=[1], progress=False)
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("x")
    with pytest.raises(PerchError, match="--overwrite"):
        synth.generate(box_models, busy, 1, targets=[1], progress=False)
    assert (busy / "keep.txt").read_text() == "x"
    assert not list(tmp_path.glob(".*partial*")), "a failed run left a partial folder behind"
