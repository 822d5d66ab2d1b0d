"""tools/brightness_probe.py: the photo's brightness over the render's at the ground truth, on a photo
made from the render itself with a known gain per channel."""

import numpy as np
import pytest
from _device import DEVICE
from _tools import load_tool
from PIL import Image

from perch_warp import bop
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine
from perch_warp.image import save_png
from perch_warp.scene import write_obj
from perch_warp.table import model_to_camera

GAIN = np.array([0.5, 0.8, 1.25])  # the photo's R, G, B over the render's


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, random_weights):
    """A one-image BOP dataset whose photo is the demo box's own render at the truth times GAIN, on black,
    with the left half of the box hidden in mask_visib (a hidden part must not count)."""
    root = tmp_path_factory.mktemp("probe")
    sc = demo_scene(seed=3)
    gx, gy, gyaw = sc.truth_xy_yaw
    R, t = (a[0] for a in model_to_camera(sc.table, sc.resting, gx, gy, gyaw))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    engine = Engine(sc.mesh, random_weights, DEVICE)
    rgb, mask = engine.render(sc.camera, T)
    photo = np.zeros_like(rgb)
    photo[mask] = rgb[mask] * GAIN
    cut = int(np.median(np.nonzero(mask)[1]))  # the box's left half is hidden: bright, and not in mask_visib
    photo[:, :cut] = 1.0
    visib = mask.copy()
    visib[:, :cut] = False
    scene = root / "test" / "000001"
    (scene / "rgb").mkdir(parents=True)
    (scene / "mask_visib").mkdir()
    save_png(scene / "rgb" / "000001.png", np.round(np.clip(photo, 0, 1) * 255).astype(np.uint8))
    save_png(scene / "mask_visib" / "000001_000000.png", visib.astype(np.uint8) * 255)
    (root / "models").mkdir()
    write_obj(sc.mesh, root / "models" / "obj_000001.obj")
    cam = {
        "cam_K": sc.camera.K.reshape(-1).tolist(),
        "cam_R_w2c": sc.table.R_t2c.reshape(-1).tolist(),
        "cam_t_w2c": (sc.table.t_t2c_m * 1000).tolist(),
        "depth_scale": 1.0,
    }
    gt = {"obj_id": 1, "cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": (t * 1000).tolist()}
    bop.write_scene(scene, {1: cam}, {1: [gt]})
    assert mask.sum() > 500 and visib.sum() > 200 and (mask & ~visib).sum() > 50
    return root


def test_ratio_is_the_photos_gain_over_the_visible_render(dataset, tmp_path, capsys):
    tool = load_tool("brightness_probe")
    out = tmp_path / "ratios.csv"
    assert tool.main(["--dataset", str(dataset), "--csv", str(out)]) == 0
    rows = out.read_text().splitlines()
    assert len(rows) == 2
    row = dict(zip(rows[0].split(","), rows[1].split(","), strict=True))
    got = np.array([float(row[f"ratio_{c}"]) for c in "rgb"])
    assert np.allclose(got, GAIN, rtol=0.02), got  # 8-bit rounding of the photo only
    # the share at white, on the visible pixels only: the hidden half is all white and must not count
    photo = np.asarray(Image.open(dataset / "test" / "000001" / "rgb" / "000001.png"))
    visib = np.asarray(Image.open(dataset / "test" / "000001" / "mask_visib" / "000001_000000.png")) > 0
    clipped = (photo[visib] == 255).any(axis=1).mean()
    assert 0.0 < clipped < 0.5 and np.isclose(float(row["clipped"]), clipped), (row["clipped"], clipped)
    assert "1 targets" in capsys.readouterr().out


def test_a_dataset_without_visible_masks_is_a_one_line_error(dataset, tmp_path, capsys):
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(dataset, bare)
    shutil.rmtree(bare / "test" / "000001" / "mask_visib")
    tool = load_tool("brightness_probe")
    assert tool.main(["--dataset", str(bare)]) == 1
    err = capsys.readouterr().err.strip()
    assert "mask_visib" in err and "--whole-render" in err and "\n" not in err
    assert tool.main(["--dataset", str(bare), "--whole-render"]) == 0  # the whole render, hidden part included
