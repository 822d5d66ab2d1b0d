"""tools/accuracy_report.py: the four accuracy figures of an eval run with intervals, and paired differences."""

import json

import pytest
from _tools import eval_run, load_tool

COLS = ["scene_id", "im_id", "inst", "obj_id", "adds_mm", "add_mm", "te_mm"]


@pytest.fixture(scope="module")
def tool():
    return load_tool("accuracy_report")


def _run(folder, rows: list[tuple]):
    return eval_run(folder, COLS, rows)


def test_figures_and_paired_differences_by_hand(tool, tmp_path, capsys):
    # ADD-S 5 mm, 30 mm, 120 mm and a failed target: AUC = (95 + 70 + 0 + 0) / 4 = 41.25; < 2 cm: 25 %.
    run = _run(
        tmp_path / "a",
        [(1, 1, 0, 9, 5, 8, 4), (1, 2, 0, 9, 30, 30, 25), (1, 3, 0, 9, 120, 150, 90), (1, 4, 0, 9, "", "", "")],
    )
    # The baseline has the first target at 25 mm (so it crosses 2 cm) and one target the run lacks.
    base = _run(tmp_path / "b", [(1, 1, 0, 9, 25, 25, 15), (1, 2, 0, 9, 30, 30, 25), (1, 5, 0, 9, 1, 1, 1)])
    out = tmp_path / "r.json"
    assert tool.main([str(run), "--against", str(base), "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    f = rep["figures"]
    assert rep["n"] == 4
    assert f["auc"]["value"] == pytest.approx(41.25)
    assert f["adds_below_2cm_pct"]["value"] == pytest.approx(25.0)
    assert f["auc_add"]["value"] == pytest.approx((92 + 70) / 4)
    assert f["te_below_1cm_pct"]["value"] == pytest.approx(25.0)
    for v in f.values():
        assert v["ci95"][0] <= v["value"] <= v["ci95"][1]
    p = rep["paired"]
    assert p["n"] == 2  # (1, 1, 0) and (1, 2, 0)
    assert p["figures"]["auc"]["diff"] == pytest.approx(((95 - 75) + 0) / 2)
    assert p["figures"]["adds_below_2cm_pct"]["diff"] == pytest.approx(50.0)
    assert p["now_below_2cm"] == [[1, 1, 0]] and p["no_longer_below_2cm"] == []
    assert p["sign_test_p"] == pytest.approx(1.0)  # one discordant target: 2 * 1/2, capped at 1
    text = capsys.readouterr().out
    assert "ADD-S AUC" in text and "here only: 1 (1/1/0); there only: 0;" in text


def test_sign_test_by_hand(tool):
    # 6 gained, 3 lost of 9 discordant: 2 * (1 + 9 + 36 + 84) / 512 = 0.5078 (stop 43's figure);
    # 4 and 2: 2 * (1 + 6 + 15) / 64 = 0.6875 (stop 47's); 5 and 0: 2 / 32.
    assert tool.sign_test_p(6, 3) == pytest.approx(260 / 512)
    assert tool.sign_test_p(3, 6) == pytest.approx(260 / 512)
    assert tool.sign_test_p(4, 2) == pytest.approx(44 / 64)
    assert tool.sign_test_p(5, 0) == pytest.approx(2 / 32)
    assert tool.sign_test_p(0, 0) == 1.0


def test_missing_folder_is_a_one_line_error(tool, tmp_path, capsys):
    assert tool.main([str(tmp_path / "nope")]) == 1
    assert "per_target.csv not found" in capsys.readouterr().err
