"""tools/compare_runs.py pairs targets of two eval runs and counts equal poses."""

import pytest
from _tools import eval_run, load_tool

COLS = [
    "scene_id",
    "im_id",
    "inst",
    "obj_id",
    "x_est_m",
    "y_est_m",
    "yaw_est_deg",
    "score",
    "time_s",
    "n_candidates",
    "n_evaluated",
]


@pytest.fixture(scope="module")
def tool():
    return load_tool("compare_runs")


def _run(folder, rows: list[tuple]):
    return eval_run(folder, COLS, rows)


def test_counts_same_poses_and_who_scores_higher(tool, tmp_path, capsys):
    ref = _run(
        tmp_path / "a",
        [
            (1, 1, 0, 9, 0.10, 0.20, 359.95, 0.5, 2.0, 100, 100),
            (1, 2, 0, 9, 0.0, 0.0, 10.0, 0.6, 4.0, 100, 100),
            (1, 3, 0, 9, 0.0, 0.0, 0.0, 0.4, 6.0, 100, 100),
            (1, 4, 0, 9, 0.0, 0.0, 0.0, 0.4, 9.0, 100, 100),
        ],
    )
    other = _run(
        tmp_path / "b",
        [
            (1, 1, 0, 9, 0.1004, 0.20, 0.02, 0.5, 1.0, 100, 20),
            (1, 2, 0, 9, 0.02, 0.0, 10.0, 0.55, 1.0, 100, 50),
            (1, 3, 0, 9, 0.0, 0.0, 20.0, 0.45, 4.0, 100, 80),
        ],
    )
    assert tool.main([str(ref), str(other)]) == 0
    out = capsys.readouterr().out
    assert "targets in both runs   3 (1 in only one, ignored)" in out
    assert "same pose              1 / 3" in out  # yaw 359.95 vs 0.02 wraps; 0.4 mm is within tolerance
    assert "reference scores higher 1" in out and "other scores higher     1" in out
    assert "scene 1 image 2 inst 0 (obj 9)" in out and "scene 1 image 3 inst 0" in out
    assert "reference  mean 4.00 s per target, scored 100.0 %" in out  # the shared targets only
    assert "other      mean 2.00 s per target, scored 50.0 %" in out


def test_missing_run_is_a_one_line_error(tool, tmp_path, capsys):
    assert tool.main([str(tmp_path / "nope"), str(tmp_path / "nope2")]) == 1
    err = capsys.readouterr().err.strip()
    assert "per_target.csv not found" in err and "\n" not in err
