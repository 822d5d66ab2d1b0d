"""The table top's extent (issue 17 (i)): points inside the polygon, the camera file's table_extent_mm,
--table-extent, and a search that never scores a pose whose model origin is off the table."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp.cli import main
from perch_warp.demo import demo_scene, write_scene
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.search_space import SearchSpace
from perch_warp.table import Table


def _table(extent=None) -> Table:
    return Table(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 0.8]), extent)


def test_contains_against_half_planes_and_a_concave_polygon():
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-1, 1, (2, 2000))
    # A convex polygon (counter-clockwise): inside = on the left of every edge.
    poly = np.array([[-0.5, -0.4], [0.6, -0.3], [0.7, 0.5], [-0.2, 0.6]])
    e = np.roll(poly, -1, axis=0) - poly
    left = np.all(e[:, 0, None] * (y - poly[:, 1, None]) - e[:, 1, None] * (x - poly[:, 0, None]) > 0, axis=0)
    assert np.array_equal(_table(poly).contains(x, y), left)
    # An L: the unit square without its upper-right quarter.
    ell = np.array([[0, 0], [1, 0], [1, 0.5], [0.5, 0.5], [0.5, 1], [0, 1]])
    want = (0 < x) & (x < 1) & (0 < y) & (y < 1) & ~((x > 0.5) & (y > 0.5))
    assert np.array_equal(_table(ell).contains(x, y), want)
    assert _table().contains(x, y).all()


def test_extent_from_the_camera_file_and_refusals():
    entry = {"cam_R_w2c": np.diag([1.0, -1.0, -1.0]).reshape(-1).tolist(), "cam_t_w2c": [0, 0, 800]}
    t = Table.from_entry({**entry, "table_extent_mm": [[-300, -200], [300, -200], [300, 200], [-300, 200]]})
    assert np.allclose(t.extent_m, [[-0.3, -0.2], [0.3, -0.2], [0.3, 0.2], [-0.3, 0.2]])
    assert Table.from_entry(entry).extent_m is None
    with pytest.raises(PerchError, match="cam.json: the table extent must be 3 or more"):
        Table.from_entry({**entry, "table_extent_mm": [[0, 0], [1, 1]]}, source="cam.json")
    with pytest.raises(PerchError, match="encloses no area"):
        Table.from_entry({**entry, "table_extent_mm": [[0, 0], [1, 1], [2, 2]]})
    with pytest.raises(PerchError, match="table_extent_mm must be a list"):
        Table.from_entry({**entry, "table_extent_mm": [[0, 0], [1], [2, 2]]})


def test_no_pose_off_the_table_is_scored_and_pruned_equals_exhaustive(random_weights):
    sc = demo_scene(seed=1)
    gx, gy, _ = sc.truth_xy_yaw
    cx, cy = round(gx / 0.02) * 0.02, round(gy / 0.02) * 0.02
    space = SearchSpace((cx - 0.06, cx + 0.06), (cy - 0.06, cy + 0.06), 0.02, (0, 2 * math.pi), math.radians(45))
    # The table ends 3 cm left of the object's true place: the true place is off it.
    table = sc.table.with_extent([[-1, -1], [gx - 0.03, -1], [gx - 0.03, 1], [-1, 1]])
    results = {}
    for search in ("exhaustive", "pruned"):
        engine = Engine(sc.mesh, random_weights, DEVICE, EngineConfig(search=search, refine=False, top_k=3))
        results[search] = engine.estimate(sc.image, sc.camera, table, sc.resting, space)
    ex, pr = results["exhaustive"], results["pruned"]
    assert [(c.x_m, c.y_m, c.yaw_rad) for c in ex.top_k] == [(c.x_m, c.y_m, c.yaw_rad) for c in pr.top_k]
    assert all(c.x_m < gx - 0.03 for c in ex.top_k)
    x, y, yaw = space.candidates()
    scores = engine.score(sc.image, sc.camera, table, sc.resting, x, y, yaw)
    off = x >= gx - 0.03
    assert off.any() and np.all(scores[off] == -np.inf) and np.isfinite(scores[~off]).any()
    assert ex.n_scored == int(np.isfinite(scores).sum())


def test_cli_table_extent(tmp_path, capsys):
    sc = demo_scene(seed=2)
    write_scene(sc, tmp_path)
    gx, gy, _ = sc.truth_xy_yaw
    x, y = round(gx, 2), round(gy, 2)
    base = [
        str(tmp_path / "rgb" / "000001.png"), "--mesh", str(tmp_path / "models" / "obj_000001.obj"),
        "--camera", str(tmp_path / "scene_camera.json"), "--device", "cpu", "--yaw-step", "45", "--no-refine",
        "--rest", "upright", "--xy-step", "0.02", "--out", str(tmp_path / "r.json"),
    ]  # fmt: skip
    # The visible table cut to the extent's box, x-0.04..x+0.04 by y-0.04..y+0.04 snapped out to the 2 cm grid.
    extent = ["--table-extent", f"{x - 0.04}", f"{x + 0.04}", f"{y - 0.04}", f"{y + 0.04}"]
    assert main([*base, *extent]) == 0
    err = capsys.readouterr().err
    assert "only where the model origin is on the table extent (4 corners)" in err
    r = json.loads((tmp_path / "r.json").read_text())
    assert 5 * 5 * 8 <= r["n_candidates"] <= 6 * 6 * 8
    assert abs(r["pose"]["x_m"] - x) <= 0.04 + 1e-9 and abs(r["pose"]["y_m"] - y) <= 0.04 + 1e-9
    assert main([*base, "--table-extent", "1", "0", "0", "1"]) == 1
    assert "--table-extent takes X0 X1 Y0 Y1 with X0 < X1" in capsys.readouterr().err
