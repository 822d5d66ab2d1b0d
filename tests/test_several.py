"""Several objects in one call (issue 19 part 2): the CLI end to end on the demo scene, on Warp's CPU device.

The demo box is searched twice, as two objects: both searches find the same best place, which one image
region cannot explain twice, so the joint step must keep one object's own best and move the other to a
peak that conflicts with it in neither footprint nor silhouette."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from perch_warp.cli import main
from perch_warp.demo import demo_scene, write_scene
from perch_warp.joint import footprint, footprint_overlap_m
from perch_warp.mesh import load_mesh


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, object]:
    d = tmp_path_factory.mktemp("several")
    sc = demo_scene(seed=2)
    write_scene(sc, d)
    return d, sc


def _args(d: Path, sc, meshes: int, out: Path, extra: list[str]) -> list[str]:
    gx, gy, _ = sc.truth_xy_yaw
    x, y = round(gx, 2), round(gy, 2)
    region = ["--x-range", f"{x - 0.2}", f"{x + 0.06}", "--y-range", f"{y - 0.06}", f"{y + 0.18}"]
    mesh = str(d / "models" / "obj_000001.obj")
    return [
        str(d / "rgb" / "000001.png"),
        *(a for _ in range(meshes) for a in ("--mesh", mesh)),
        "--camera", str(d / "scene_camera.json"),
        "--device", "cpu", "--search", "pruned", "--xy-step", "0.02", "--yaw-step", "45", "--rest", "upright",
        "--refine-xy", "0.01", "--refine-yaw", "15",
        *region, "--out", str(out), "--quiet", *extra,
    ]  # fmt: skip


def test_two_objects_one_place_the_joint_step_separates_them(scene, tmp_path, capsys):
    d, sc = scene
    assert main(_args(d, sc, 1, tmp_path / "one.json", ["--refine-peaks", "4"])) == 0
    one = json.loads((tmp_path / "one.json").read_text())
    pics = ["--overlay", str(tmp_path / "o.png"), "--heatmap", str(tmp_path / "h.png")]
    assert main(_args(d, sc, 2, tmp_path / "two.json", ["--joint-peaks", "4", "--occluders", "none", *pics])) == 0
    printed = capsys.readouterr().out
    two = json.loads((tmp_path / "two.json").read_text())
    a, b = two["objects"]
    # Each object's own search is the one-object search with the same peaks refined.
    for o in (a, b):
        assert o["joint"]["own_best"] == one["pose"]
        assert sorted(p["score"] for p in o["joint"]["peaks"]) == sorted(p["score"] for p in one["refine"]["peaks"])
    # Both wanted the same place: the first keeps it, the second moves to another peak.
    assert a["pose"] == one["pose"] and not a["joint"]["changed"]
    assert b["joint"]["changed"] and b["joint"]["peak"] > 0
    assert b["pose"] == b["joint"]["peaks"][b["joint"]["peak"]]
    assert two["joint"]["method"] == "exact" and two["joint"]["combinations"] == len(a["joint"]["peaks"]) ** 2
    assert two["joint"]["conflicts"] == [] and two["joint"]["picks"] == [0, b["joint"]["peak"]]
    assert math.hypot(a["pose"]["x_m"] - b["pose"]["x_m"], a["pose"]["y_m"] - b["pose"]["y_m"]) >= 0.05
    assert two["joint"]["moved"] == [{"object": 1, "by": 0, "why": two["joint"]["moved"][0]["why"]}]
    why = two["joint"]["moved"][0]["why"]  # one place: their footprints overlap, or one hides the other
    assert why.startswith("footprints overlap by") or "hidden behind" in why
    assert "joint step: exact over" in printed
    assert f"changed obj_000001.obj #2 ({why} with obj_000001.obj #1)" in printed
    assert Image.open(tmp_path / "o.png").size[0] == sc.camera.width
    assert sorted(p.name for p in tmp_path.glob("h_*.png")) == ["h_1_obj_000001.png", "h_2_obj_000001.png"]
    # The answers' footprints on the table overlap by no more than the tolerance.
    hull = load_mesh(str(d / "models" / "obj_000001.obj")).hull_points_m()
    polys = [footprint(sc.table, _pose(o["pose"]), hull) for o in (a, b)]
    assert footprint_overlap_m(*polys) <= 0.01


def _pose(p: dict) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(p["cam_R_m2c"]).reshape(3, 3)
    T[:3, 3] = np.asarray(p["cam_t_m2c_mm"]) / 1000.0
    return T


def _two_copies_eval(scene, tmp_path: Path) -> list[str]:
    """eval --joint's arguments on a BOP dataset whose one image holds two copies of the demo box at the same
    pose (obj 1 and obj 2, the same mesh)."""
    d, sc = scene
    ds = tmp_path / "ds"
    scene_dir = ds / "test" / "000001"
    shutil.copytree(d / "rgb", scene_dir / "rgb")
    shutil.copy(d / "scene_camera.json", scene_dir)
    shutil.copytree(d / "models", ds / "models")
    shutil.copy(ds / "models" / "obj_000001.obj", ds / "models" / "obj_000002.obj")
    gt = json.loads((d / "scene_gt.json").read_text())
    gt["1"].append({**gt["1"][0], "obj_id": 2})
    (scene_dir / "scene_gt.json").write_text(json.dumps(gt))
    gx, gy, _ = sc.truth_xy_yaw
    x, y = round(gx, 2), round(gy, 2)
    args = [
        "eval", "--dataset", str(ds), "--out", str(tmp_path / "out"), "--joint", "--joint-peaks", "4",
        "--device", "cpu", "--search", "pruned", "--xy-step", "0.02", "--yaw-step", "45",
        "--refine-xy", "0.01", "--refine-yaw", "15", "--no-plots",
        "--x-range", f"{x - 0.2}", f"{x + 0.06}", "--y-range", f"{y - 0.06}", f"{y + 0.18}",
    ]  # fmt: skip
    return args


def test_eval_joint_pairs_each_target_with_its_own_answer(scene, tmp_path, capsys):
    """eval --joint on a BOP dataset whose one image holds two copies of the demo box at the same pose (obj 1
    and obj 2, the same mesh): both searches find that place, the joint step moves one of them away, and the
    summary pairs each target's joint answer with its own; a second run resumes with nothing to do."""
    args = [*_two_copies_eval(scene, tmp_path), "--occluders", "none"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    joint = summary["joint"]
    assert joint["n"] == 2 and joint["n_changed"] == 1
    (changed,) = joint["changed"]
    assert changed["own_adds_mm"] < 20.0 < changed["adds_mm"]  # its own answer was right; the place was taken
    assert joint["own"]["adds_below_2cm_pct"] == 100.0 and joint["joint"]["adds_below_2cm_pct"] == 50.0
    assert joint["auc_gain"] < 0 and joint["below_2cm_gain_pct"] == -50.0
    with (tmp_path / "out" / "per_target.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert sorted(r["joint_changed"] for r in rows) == ["False", "True"]
    journal = [json.loads(x) for x in (tmp_path / "out" / "targets.jsonl").read_text().splitlines()]
    moved = {j["obj_id"]: j["details"]["joint"]["moved_by"] for j in journal}
    (mover,) = [k for k, v in moved.items() if v]  # the moved target names the other, which stays
    assert [m["obj_id"] for m in moved[mover]] == [3 - mover] and moved[3 - mover] == []
    assert all(float(r["own_adds_mm"]) < 20.0 for r in rows)
    assert "Joint step (eval --joint): changed 1 of 2 answers" in printed
    assert main(args) == 0  # resumed: both targets journalled, nothing searched again
    assert "resuming" not in capsys.readouterr().err


def test_eval_joint_occluders_pairs_the_second_pass_with_the_first(scene, tmp_path, capsys):
    """eval --joint --occluders answers: each target searched again with the other target's first-pass answer
    hiding what it covers; the journal keeps the first pass's joint answer beside the second's, the summary
    pairs them, and eval_config.json records the option, the default with --joint (a run with
    --occluders none would not resume this one)."""
    args = _two_copies_eval(scene, tmp_path)
    assert main(args) == 0
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    second = summary["occluders"]
    assert second["n"] == 2 and set(second) >= {"first_pass", "second_pass", "auc_gain_ci95"}
    journal = [json.loads(x) for x in (tmp_path / "out" / "targets.jsonl").read_text().splitlines()]
    for j in journal:
        occ = j["details"]["occluders"]
        assert occ["occluders"] == 1 and occ["beta"] == 0.25 and occ["cells_covered"] > 0
        assert np.asarray(occ["first_R_m2c"]).shape == (3, 3) and len(occ["first_t_m2c_m"]) == 3
        # The second pass took the first pass's scores where the other answer hides nothing.
        assert occ["scores_reused"] > 0 and occ["first_total_s"] > 0
    with (tmp_path / "out" / "per_target.csv").open() as f:
        rows = list(csv.DictReader(f))
    # The first pass is the plain joint run: one copy keeps the place, the other is moved off it.
    assert sorted(float(r["first_adds_mm"]) < 20.0 for r in rows) == [False, True]
    assert all(r["second_pass_changed"] in ("True", "False") for r in rows)
    assert "Second pass (--occluders answers): changed" in printed
    cost = second["cost"]  # each pass's own search time, from the journal
    assert cost["n"] == 2 and cost["first_pass_s"] == pytest.approx(sum(float(r["first_pass_s"]) for r in rows))
    assert cost["second_pass_s"] == pytest.approx(sum(j["details"]["timings_s"]["total"] for j in journal))
    assert "Second pass cost: its searches took" in printed
    config = json.loads((tmp_path / "out" / "eval_config.json").read_text())
    assert config["options"]["occluders"] == "answers"
    assert main(args) == 0  # resumed: nothing searched again
    assert "resuming" not in capsys.readouterr().err
    assert main([*args, "--occluders", "none"]) != 0  # another setting: refused, not mixed into the journal
    assert "occluders" in capsys.readouterr().err


def test_occluders_need_several_objects_or_joint(scene, tmp_path, capsys):
    d, sc = scene
    assert main(_args(d, sc, 1, tmp_path / "one.json", ["--occluders", "answers"])) != 0
    assert "--occluders answers needs several objects" in capsys.readouterr().err
    assert not (tmp_path / "one.json").exists()
    args = [a for a in _two_copies_eval(scene, tmp_path) if a != "--joint"]
    assert main([*args, "--occluders", "answers"]) != 0
    assert "--occluders answers needs --joint" in capsys.readouterr().err


def test_two_objects_report_both_passes_by_default(scene, tmp_path, capsys):
    """Several objects: the second pass (--occluders answers) runs unless --occluders none is given."""
    d, sc = scene
    assert main(_args(d, sc, 2, tmp_path / "two.json", [])) == 0
    printed = capsys.readouterr().out
    two = json.loads((tmp_path / "two.json").read_text())
    for o in two["objects"]:
        assert o["occluders"]["occluders"] == 1 and set(o["occluders"]["first_pass"]) >= {"x_m", "y_m", "score"}
        assert o["occluders"]["scores_reused"] > 0
    assert printed.count("first pass (no occluders):") == 2
