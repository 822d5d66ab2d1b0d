"""tools/grid_check.py: which grid nodes enclose the truth, and its one-line errors on bad runs."""

import json
import math

import numpy as np
import pytest
from _tools import load_tool

from perch_warp.search_space import SearchSpace


@pytest.fixture(scope="module")
def tool():
    return load_tool("grid_check")


def test_truth_between_nodes_gets_the_eight_enclosing_nodes(tool):
    space = SearchSpace((-0.05, 0.05), (0.0, 0.1), 0.01, yaw_step_rad=math.radians(5.0))
    x, y, yaw = tool.truth_nodes(space, 0.0137, 0.0421, math.radians(12.3))
    assert len(x) == 8
    assert sorted(set(np.round(x, 9))) == [0.01, 0.02]
    assert sorted(set(np.round(y, 9))) == [0.04, 0.05]
    assert sorted(set(np.round(np.degrees(yaw), 6))) == [10.0, 15.0]


def test_yaw_wraps_around_the_circle(tool):
    space = SearchSpace((0.0, 0.02), (0.0, 0.02), 0.01, yaw_step_rad=math.radians(5.0))
    _, _, yaw = tool.truth_nodes(space, 0.005, 0.005, math.radians(358.0))
    assert sorted(set(np.round(np.degrees(yaw), 6))) == [0.0, 355.0]
    _, _, yaw = tool.truth_nodes(space, 0.005, 0.005, math.radians(-1.0))  # the same turn, written negative
    assert sorted(set(np.round(np.degrees(yaw), 6))) == [0.0, 355.0]


def test_truth_at_the_region_edge_gets_the_nodes_that_exist(tool):
    space = SearchSpace((0.0, 0.05), (0.0, 0.05), 0.01, yaw_step_rad=math.radians(5.0))
    x, y, _ = tool.truth_nodes(space, -0.004, 0.0512, math.radians(2.5))
    assert sorted(set(np.round(x, 9))) == [0.0]
    assert sorted(set(np.round(y, 9))) == [0.05]


def _summary(folder, command: str):
    folder.mkdir()
    (folder / "summary.json").write_text(json.dumps({"command": command}))
    return folder


def test_a_folder_without_summary_is_a_one_line_error(tool, tmp_path, capsys):
    assert tool.main([str(tmp_path / "nothing")]) == 1
    err = capsys.readouterr().err.strip()
    assert "summary.json not found" in err and "\n" not in err


def test_a_rest_stable_run_is_refused(tool, tmp_path, capsys):
    out = _summary(tmp_path / "run", "python -m perch_warp eval --dataset d --out o --rest stable")
    assert tool.main([str(out)]) == 1
    assert "only --rest truth runs" in capsys.readouterr().err


def test_a_joint_run_is_refused(tool, tmp_path, capsys):
    out = _summary(tmp_path / "run", "python -m perch_warp eval --dataset d --out o --joint")
    assert tool.main([str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert "searched with --joint" in err and "\n" not in err


def test_a_command_that_is_not_eval_is_refused(tool, tmp_path, capsys):
    out = _summary(tmp_path / "run", "python -m perch_warp image.png --mesh m.obj")
    assert tool.main([str(out)]) == 1
    assert "not a `python -m perch_warp eval` line" in capsys.readouterr().err


def test_the_run_options_are_parsed_from_its_command(tool, tmp_path):
    cmd = "python -m perch_warp eval --dataset d --out o --search coarse-to-fine --beam 128 --ray --xy-step 0.02"
    args = tool.run_args(_summary(tmp_path / "run", cmd), device="cpu")
    assert (args.search, args.beam, args.xy_step, args.device) == ("coarse-to-fine", 128, 0.02, "cpu")


def test_a_run_without_its_journal_is_a_one_line_error(tool, tmp_path, capsys):
    out = _summary(tmp_path / "run", "python -m perch_warp eval --dataset d --out o")
    assert tool.main([str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert "per_target.csv not found" in err and "\n" not in err


def test_a_run_whose_dataset_is_gone_is_a_one_line_error(tool, tmp_path, capsys):
    out = _summary(tmp_path / "run", f"python -m perch_warp eval --dataset {tmp_path / 'gone'} --out o")
    (out / "per_target.csv").write_text("scene_id,im_id,inst,obj_id,adds_mm\n")
    (out / "targets.jsonl").write_text("")
    assert tool.main([str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("grid_check: ") and "gone" in err and "\n" not in err
