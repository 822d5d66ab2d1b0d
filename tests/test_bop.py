"""BOP reading and writing: results round trip, plane fit from depth, clear errors for bad datasets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from perch_warp import bop
from perch_warp.camera import Camera
from perch_warp.errors import PerchError
from perch_warp.paths import shared_file
from perch_warp.table import RestingPose, model_to_camera

W, H = 64, 48
K = [60.0, 0.0, 31.5, 0.0, 60.0, 23.5, 0.0, 0.0, 1.0]
# Table plane n . X + d = 0 in the camera frame: the camera looks down at 45 degrees, 0.6 m along its axis.
PLANE_N = np.array([0.0, -1.0, -1.0]) / math.sqrt(2)
PLANE_D = 0.6 / math.sqrt(2)
DEPTH_SCALE = 0.1


def plane_depth_mm(camera: Camera, n: np.ndarray, d: float) -> np.ndarray:
    """Exact depth (mm) of the plane n . X + d = 0 at every pixel; 0 where the ray misses it."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], -1)
    with np.errstate(divide="ignore"):
        z = -d / (rays @ n)
    return np.where(z > 0, z * 1000.0, 0.0)


def write_depth_png(path: Path, depth_mm: np.ndarray, depth_scale: float = DEPTH_SCALE) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(depth_mm / depth_scale).astype(np.uint16)).save(path)


def write_mesh(path: Path, kind: str) -> None:
    import trimesh

    if kind == "box":
        m = trimesh.creation.box(extents=[40.0, 30.0, 60.0])  # mm, as BOP models
    else:
        m = trimesh.creation.cylinder(radius=25.0, height=60.0, sections=24)
    m.visual.vertex_colors = np.tile([200, 40, 40, 255] if kind == "box" else [40, 40, 200, 255], (len(m.vertices), 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    m.export(path)


# Instances per image: (obj_id, x_m, y_m, yaw_rad, visib_fract). Object 7 has no mesh.
SCENE = {
    1: [(1, 0.0, 0.0, 0.3, 1.0), (1, 0.08, 0.03, 1.0, 0.55), (7, -0.05, 0.05, 0.0, 0.9), (2, -0.07, -0.03, 0.0, 0.25)],
    2: [(2, 0.02, 0.04, 2.0, 0.95), (1, -0.03, 0.0, -1.0, 0.8)],
}


def write_tiny_dataset(root: Path, with_w2c: bool = True, with_depth: bool = True, with_info: bool = True) -> Path:
    """A two-image BOP dataset (64x48) with a box (1) and a cylinder (2) standing on a tilted table."""
    import trimesh

    from perch_warp.bop import table_from_plane

    write_mesh(root / "models" / "obj_000001.ply", "box")
    write_mesh(root / "models" / "obj_000002.ply", "cylinder")
    (root / "models" / "models_info.json").write_text(
        json.dumps({"1": {"diameter": 78.1, "name": "001_box"}, "2": {"diameter": 78.1, "name": "002_cylinder"}})
    )
    table = table_from_plane(PLANE_N, PLANE_D)
    camera = Camera(np.reshape(K, (3, 3)), W, H)
    sdir = root / "test" / "000001"
    cams, gts, infos = {}, {}, {}
    rng = np.random.default_rng(0)
    for im_id, insts in SCENE.items():
        (sdir / "rgb").mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(sdir / "rgb" / f"{im_id:06d}.png")
        entry = {"cam_K": K, "depth_scale": DEPTH_SCALE}
        if with_w2c:
            entry["cam_R_w2c"] = table.R_t2c.reshape(-1).tolist()
            entry["cam_t_w2c"] = (table.t_t2c_m * 1000).tolist()
        cams[str(im_id)] = entry
        if with_depth:
            write_depth_png(sdir / "depth" / f"{im_id:06d}.png", plane_depth_mm(camera, PLANE_N, PLANE_D))
        gts[str(im_id)], infos[str(im_id)] = [], []
        for obj_id, x, y, yaw, vf in insts:
            kind = "box" if obj_id == 1 else "cylinder"
            m = (
                trimesh.creation.box(extents=[0.04, 0.03, 0.06])
                if kind == "box"
                else trimesh.creation.cylinder(radius=0.025, height=0.06, sections=24)
            )
            rest = RestingPose.upright(np.asarray(m.vertices))
            R, t = model_to_camera(table, rest, x, y, yaw)
            gts[str(im_id)].append(
                {"obj_id": obj_id, "cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": (t * 1000).tolist()}
            )
            infos[str(im_id)].append({"visib_fract": vf})
    (sdir / "scene_camera.json").write_text(json.dumps(cams))
    (sdir / "scene_gt.json").write_text(json.dumps(gts))
    if with_info:
        (sdir / "scene_gt_info.json").write_text(json.dumps(infos))
    return root


# ----------------------------------------------------------------------------- results.csv


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_results_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    rows = [
        bop.BopResult(
            int(s),
            int(i),
            int(o),
            float(rng.uniform()),
            random_rotation(rng),
            rng.normal(size=3) * 500,
            float(rng.uniform(0, 200)),
        )
        for s, i, o in [(48, 1, 3), (48, 1, 3), (49, 7, 9), (1, 1, 8)]
    ]
    path = tmp_path / "results.csv"
    bop.write_results(path, rows)
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert all(len(line.split(",")) == 7 and len(line.split(",")[4].split()) == 9 for line in lines[1:])
    back = bop.read_results(path)
    assert len(back) == len(rows)
    for a, b in zip(rows, back, strict=True):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time_s) == (b.scene_id, b.im_id, b.obj_id, b.score, b.time_s)
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t_mm, b.t_mm)


def test_malformed_results_name_file_and_line(tmp_path):
    path = tmp_path / "results.csv"
    path.write_text(
        "scene_id,im_id,obj_id,score,R,t,time\n1,1,3,0.5,1 0 0 0 1 0 0 0 1,0 0 500,1.0\n1,1,3,0.5,1 0,0 0 500,1\n"
    )
    with pytest.raises(PerchError, match=r"results\.csv line 3"):
        bop.read_results(path)
    path.write_text("scene,im\n")
    with pytest.raises(PerchError, match="header"):
        bop.read_results(path)


# ----------------------------------------------------------------------------- plane fit


def test_ransac_recovers_a_known_plane_with_outliers(tmp_path):
    camera = Camera(np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]), 320, 240)
    n = np.array([0.05, -0.8, -0.55])
    n /= np.linalg.norm(n)
    d = 0.45
    depth = plane_depth_mm(camera, n, d)
    rng = np.random.default_rng(1)
    depth = depth + rng.normal(0, 1.5, depth.shape) * (depth > 0)  # 1.5 mm sensor noise
    depth[60:140, 100:200] -= 80.0  # an object 8 cm in front of the table
    bad = rng.uniform(size=depth.shape) < 0.15  # 15% wild readings
    depth[bad] = rng.uniform(300, 3000, bad.sum())
    path = tmp_path / "depth" / "000001.png"
    write_depth_png(path, depth)
    table = bop.table_from_depth(path, camera, DEPTH_SCALE)
    z_axis = table.R_t2c[:, 2]
    assert math.degrees(math.acos(min(1.0, float(z_axis @ n)))) < 0.5  # +z = normal towards the camera
    # Distance camera -> plane, and the origin on the plane and on the optical axis.
    assert table.camera_center_table_m[2] == pytest.approx(d, abs=0.002)
    assert float(n @ table.t_t2c_m + d) == pytest.approx(0.0, abs=0.002)
    assert table.t_t2c_m[:2] == pytest.approx([0.0, 0.0], abs=1e-9)
    # x axis: the camera's x projected on the plane (deterministic choice).
    x_expected = np.array([1.0, 0, 0]) - n[0] * n
    assert float(table.R_t2c[:, 0] @ (x_expected / np.linalg.norm(x_expected))) > 0.9999


def test_plane_fit_agrees_with_the_shared_ycbv_table_frame():
    cam_file = shared_file("data", "ycbv", "test", "000002", "scene_camera.json")
    if cam_file is None:
        pytest.skip("shared/data/ycbv is not available (set PERCH_WARP_SHARED)")
    sdir = cam_file.parent
    entry = bop.load_scene_camera(cam_file)[1]
    camera = Camera(np.reshape(entry["cam_K"], (3, 3)), 640, 480)
    fitted, how = bop.table_for_image(entry, sdir, 1, camera, cam_file, how="depth")
    given, how_given = bop.table_for_image(entry, sdir, 1, camera, cam_file)
    assert (how, how_given) == ("depth RANSAC", "cam_R_w2c")
    cos = float(fitted.R_t2c[:, 2] @ given.R_t2c[:, 2])
    assert math.degrees(math.acos(min(1.0, cos))) < 1.0
    assert np.linalg.norm(fitted.t_t2c_m - given.t_t2c_m) < 0.005


# ----------------------------------------------------------------------------- bad datasets


def test_tiny_dataset_reads(tmp_path):
    ds = bop.open_dataset(write_tiny_dataset(tmp_path / "ds"))
    assert ds.scene_ids() == [1]
    assert ds.model_path(1).name == "obj_000001.ply" and ds.model_path(7) is None
    assert ds.object_name(2) == "002 cylinder" and ds.object_name(9) == "obj 9"
    gt = bop.load_scene_gt(ds.scene_dir(1) / "scene_gt.json")
    assert [g.obj_id for g in gt[1]] == [1, 1, 7, 2]
    assert np.all(np.abs(gt[1][0].t_m2c_m) < 2.0)  # converted to metres


def test_missing_scene_gt_names_the_file(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    (root / "test" / "000001" / "scene_gt.json").unlink()
    with pytest.raises(PerchError, match=r"scene_gt\.json not found: .*000001/scene_gt\.json"):
        bop.select_targets(bop.open_dataset(root))


def test_malformed_json_names_the_file(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    (root / "test" / "000001" / "scene_camera.json").write_text('{"1": {"cam_K": [1, 2,')
    with pytest.raises(PerchError, match=r"malformed JSON in .*scene_camera\.json"):
        bop.select_targets(bop.open_dataset(root))


def test_bad_pose_values_name_the_file_and_instance(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    path = root / "test" / "000001" / "scene_gt.json"
    data = json.loads(path.read_text())
    data["2"][1]["cam_t_m2c"] = [1, 2]
    path.write_text(json.dumps(data))
    with pytest.raises(PerchError, match=r"scene_gt\.json: image 2 instance 1 cam_t_m2c"):
        bop.load_scene_gt(path)


def test_image_size_mismatch_names_the_image(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    img = root / "test" / "000001" / "rgb" / "000002.png"
    Image.fromarray(np.zeros((96, 128, 3), dtype=np.uint8)).save(img)  # twice the calibrated size
    with pytest.raises(PerchError, match=r"rgb/000002\.png is 128x96"):
        bop.select_targets(bop.open_dataset(root))
    Image.fromarray(np.zeros((24, 32, 3), dtype=np.uint8)).save(img)  # half: principal point outside
    with pytest.raises(PerchError, match=r"000002\.png"):
        bop.select_targets(bop.open_dataset(root))


def test_root_camera_json_size_is_checked(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    (root / "camera.json").write_text(json.dumps({"width": 640, "height": 480}))
    with pytest.raises(PerchError, match=r"64x48 but .*camera\.json says 640x480"):
        bop.select_targets(bop.open_dataset(root))


def test_model_listed_without_mesh_is_an_error(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    (root / "models" / "obj_000002.ply").unlink()
    with pytest.raises(PerchError, match=r"models_info\.json lists object 2 but its mesh .*obj_000002"):
        bop.select_targets(bop.open_dataset(root))
    with pytest.raises(PerchError, match=r"no mesh for object 7: expected .*obj_000007\.obj"):
        bop.select_targets(bop.open_dataset(root), objects=[1, 7])


def test_no_table_frame_and_no_depth_is_a_clear_error(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds", with_w2c=False, with_depth=False)
    with pytest.raises(PerchError, match=r"no table frame .*cam_R_w2c.*depth image"):
        bop.select_targets(bop.open_dataset(root))
    # With depth it falls back to a plane fit that finds the table used to make the dataset.
    root = write_tiny_dataset(tmp_path / "ds2", with_w2c=False, with_depth=True)
    sel = bop.select_targets(bop.open_dataset(root))
    im = sel.images[0]
    table, how = bop.table_for_image(im.entry, im.rgb.parent.parent, im.im_id, im.camera, im.camera_file)
    assert how == "depth RANSAC"
    assert float(table.R_t2c[:, 2] @ PLANE_N) > math.cos(math.radians(0.5))


def test_dataset_info_models_dir_and_override(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds")
    (root / "models").rename(tmp_path / "meshes")
    with pytest.raises(PerchError, match="models folder not found"):
        bop.open_dataset(root)
    assert bop.open_dataset(root, models_dir=tmp_path / "meshes").model_path(1) is not None
    (root / "dataset_info.json").write_text(json.dumps({"models_dir": str(tmp_path / "meshes")}))
    assert bop.open_dataset(root).models_dir == tmp_path / "meshes"
