"""The speed-measuring tools measure the right thing: ray hits against an independent
intersector, the engine's ray count against the boxes' areas, and bench's report."""

import json
import math
import sys

import numpy as np
import pytest
import trimesh
import warp as wp

from perch_warp import bench
from perch_warp.camera import Camera
from perch_warp.cli import main
from perch_warp.demo import demo_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.mesh import ObjectMesh
from perch_warp.render import project_boxes
from perch_warp.search_space import SearchSpace
from perch_warp.table import model_to_camera, rot_z

CAM = Camera(np.array([[60.0, 0, 23.5], [0, 60.0, 17.5], [0, 0, 1]]), 48, 36)


def _sphere() -> ObjectMesh:
    s = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    V = np.asarray(s.vertices, np.float64) * [1.0, 0.7, 1.3]  # an ellipsoid: no symmetry hides a wrong rotation
    return ObjectMesh(V, np.asarray(s.faces, np.int32), vertex_colors=np.full((len(V), 3), 0.5, np.float32))


def _poses() -> tuple[np.ndarray, np.ndarray]:
    """Two model -> camera poses: one in the middle of the view, one half outside its right edge."""
    tipped = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # 90 deg about x, so all three axes matter
    R = np.stack([rot_z(0.4), rot_z(-1.1) @ tipped])
    t = np.array([[0.0, 0.01, 0.4], [0.17, -0.02, 0.45]])
    return R, t


def _moller_trumbore(orig: np.ndarray, dirs: np.ndarray, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Nearest hit parameter (float64) of each ray (N, 3) with the triangles, MISS where none."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e1, e2 = b - a, c - a
    p = np.cross(dirs[:, None, :], e2[None])
    det = np.einsum("fk,nfk->nf", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = orig[:, None, :] - a[None]
        u = np.einsum("nfk,nfk->nf", s, p) * inv
        q = np.cross(s, e1[None])
        v = np.einsum("nk,nfk->nf", dirs, q) * inv
        t = np.einsum("fk,nfk->nf", e2, q) * inv
    ok = (np.abs(det) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(ok, t, np.inf).min(1)
    return np.where(np.isfinite(t), t, bench.MISS)


def _reference_hits(mesh: ObjectMesh, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Independent rays (model frame, float64) through every pixel, intersected in NumPy: (P, H, W)."""
    v, u = np.mgrid[0 : CAM.height, 0 : CAM.width]
    d_c = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones(u.shape)], -1).reshape(-1, 3)
    out = []
    for Ri, ti in zip(R, t, strict=True):
        origin = -Ri.T @ ti  # the camera centre in the model frame
        dirs = d_c @ Ri  # R^T d for row vectors
        out.append(_moller_trumbore(np.tile(origin, (len(dirs), 1)), dirs, mesh.vertices_m, mesh.faces))
    return np.stack(out).reshape(len(R), CAM.height, CAM.width)


def _wp_mesh(mesh: ObjectMesh) -> wp.Mesh:
    return wp.Mesh(
        points=wp.array(mesh.vertices_m.astype(np.float32), dtype=wp.vec3, device="cpu"),
        indices=wp.array(mesh.faces.reshape(-1), dtype=wp.int32, device="cpu"),
    )


def test_microbenchmark_hits_match_moller_trumbore():
    mesh = _sphere()
    R, t = _poses()
    got, stats = bench.warp_raycast(_wp_mesh(mesh), CAM, R, t, "cpu")
    want = _reference_hits(mesh, R, t)
    assert got.shape == want.shape == (2, CAM.height, CAM.width)
    hit_got, hit_want = got != bench.MISS, want != bench.MISS
    assert 100 < hit_want.sum() < hit_want.size  # both hits and misses are checked
    assert hit_want[1][:, -1].any() and not hit_want[0][:, -1].any()  # the second pose is cut by the image edge
    assert np.array_equal(hit_got, hit_want)
    # Hit parameter = depth along the optical axis (the ray's camera-frame z is 1), metres.
    assert np.allclose(got[hit_got], want[hit_want], rtol=0, atol=1e-5)
    assert stats["rays_per_launch"] == 2 * CAM.width * CAM.height and stats["rays_per_s"] > 0


def test_peer_casts_the_same_rays():
    # ImportError too: an installed open3d can lack its system libraries (e.g. libusb) and is then no peer.
    pytest.importorskip(
        "open3d", reason="open3d not importable (optional: pip install '.[bench]')", exc_type=ImportError
    )
    mesh = _sphere()
    R, t = _poses()
    t_warp, _ = bench.warp_raycast(_wp_mesh(mesh), CAM, R, t, "cpu")
    t_peer, stats = bench.open3d_raycast(mesh, CAM, R, t)
    cmp = bench.compare_hits(t_warp, t_peer)
    assert cmp["agreement_ok"] and cmp["rays"] == t_warp.size
    assert cmp["depth_abs_diff_max_m"] < 1e-5
    assert stats["rays_per_launch"] == t_warp.size


def test_compare_hits_counts_disagreements():
    a = np.array([1.0, bench.MISS, 2.0, bench.MISS], np.float32)
    b = np.array([1.5, bench.MISS, bench.MISS, 3.0], np.float32)
    c = bench.compare_hits(a, b)
    assert c["agreement"] == 0.5 and c["disagreeing_rays"] == 2 and not c["agreement_ok"]
    assert c["depth_abs_diff_max_m"] == pytest.approx(0.5)


def test_missing_open3d_is_said_not_silent(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` fail as if not installed
    assert bench.peer_unavailable_reason() == bench.PEER_NOT_INSTALLED
    assert "pip install open3d" in bench.PEER_NOT_INSTALLED


def test_engine_counts_the_rendered_box_areas(random_weights):
    sc = demo_scene(seed=1)
    gx, gy, _ = sc.truth_xy_yaw
    space = SearchSpace((gx - 0.02, gx + 0.02), (gy - 0.02, gy + 0.02), 0.02, (0, 2 * math.pi), math.radians(90))
    args = (sc.image, sc.camera, sc.table, sc.resting, space)
    one = Engine(sc.mesh, random_weights, "cpu", EngineConfig(refine=False)).estimate(*args)
    many = Engine(sc.mesh, random_weights, "cpu", EngineConfig(batch_pixels=3000, refine=False)).estimate(*args)
    assert one.n_scored == len(space)  # every candidate was rendered
    # Independently: each candidate's box bounds the projection of all mesh vertices.
    x, y, yaw = space.candidates()
    R, t = model_to_camera(sc.table, sc.resting, x, y, yaw)
    boxes = project_boxes(sc.camera, sc.mesh.vertices_m, R, t)
    assert np.all(boxes[:, 2:] > 0)
    assert one.info.rays == int((boxes[:, 2].astype(np.int64) * boxes[:, 3]).sum())
    assert many.info.batches > one.info.batches and many.info.rays == one.info.rays


def test_bench_writes_the_promised_report(shared, caffe_weights, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "open3d", None)  # the peer must then be reported as skipped, not dropped
    args = ["bench", "--device", "cpu", "--clip", "0.04", "--xy-step", "0.02", "--yaw-step", "1.6", "--no-refine"]
    args += ["--image-scale", "0.25", "--ray-poses", "2", "--min-time", "0", "--out", str(tmp_path)]
    args += ["--score", "shift=1"]
    assert main(args) == 0
    out = capsys.readouterr().out
    r = json.loads((tmp_path / "bench.json").read_text())
    text = (tmp_path / "bench.txt").read_text()
    assert text.strip() in out
    for key in ("device", "device_name", "commit", "command", "settings", "search", "memory", "raycast", "setup_s"):
        assert key in r, key
    assert r["settings"]["score"] == "shift=1"
    s = r["search"]
    # "bound": the pruned search's only; "refine": not with --no-refine
    assert set(bench.STAGES) - {"bound", "refine"} <= set(s["timings_s_mean"])
    assert (
        s["candidates_in_space"] == s["candidates_evaluated"] > 0
        and 0 < s["candidates_scored"] <= s["candidates_in_space"]
    )
    assert s["rays_per_run"] > 0 and s["candidates_per_s"] > 0 and s["rays_per_s_render"] > 0
    assert len(s["runs"]) == 1 and "wall_s" in s["warmup"] and s["adds_m"] >= 0
    assert r["memory"]["host_peak_mib"] > 0 and r["memory"]["device_peak_mib"] is None
    rc = r["raycast"]
    assert rc["image"] == r["search_image"] == [160, 120]
    assert rc["warp"]["rays_per_launch"] == rc["poses"] * 160 * 120 and rc["hit_fraction"] > 0
    assert rc["peer"] == {"skipped": bench.PEER_NOT_INSTALLED}
    assert bench.PEER_NOT_INSTALLED in text and "ADD-S" in text and "rays/s" in text
    assert r["commit"] == "unknown" or len(r["commit"]) >= 4


def test_bench_bad_options_are_one_line_errors(shared, tmp_path, capsys):
    for extra, words in (
        (["--repeat", "0"], "--repeat"),
        (["--warmup", "-1"], "--warmup"),
        (["--obj", "99"], "object 99"),
        (["--clip", "-1"], "--clip"),
        (["--score", "shift=9"], "shift"),
    ):
        assert main(["bench", "--device", "cpu", "--out", str(tmp_path), *extra]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("perch_warp: error: ") and words in err[0], err


def test_commit_named_by_environment_overrides_git(monkeypatch):
    monkeypatch.setenv(bench.ENV_COMMIT, "abc1234")
    assert bench.git_commit() == "abc1234"
    assert bench.git_dirty() is None
    monkeypatch.delenv(bench.ENV_COMMIT)
    assert bench.git_commit() != "abc1234"
