"""tools/conv_compare.py: both conv forms on the same real boxes, the same points and values."""

import json

import pytest
from _device import DEVICE
from _tools import load_tool


def test_conv_forms_agree_on_real_boxes(shared, caffe_weights, tmp_path):
    tool = load_tool("conv_compare")
    out = tmp_path / "conv.json"
    args = ["--dataset", str(shared / "data" / "ycbv"), "--device", DEVICE, "--poses", "6", "--repeat", "1"]
    assert tool.main([*args, "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["same_points_on_mask"] and r["candidates"] > 0 and 0 < r["on_mask_points"] < r["feature_points"]
    assert r["max_abs_difference"] < 1e-5
    assert set(r["seconds"]) == {"warp", "torch"}
    # Caffe conv1: 96 filters of 3 x 11 x 11, a multiply and an add each, at every feature point
    # (torch's conv2d) or at the points on the mask (the Warp kernel).
    per_point = 2 * 96 * 3 * 121 / 1e9
    assert r["conv1_gflop"]["torch"] == pytest.approx(per_point * r["feature_points"])
    assert r["conv1_gflop"]["warp"] == pytest.approx(per_point * r["on_mask_points"])
    assert all(r["gflop_per_s"][k] * r["seconds"][k] == pytest.approx(r["conv1_gflop"][k]) for k in r["seconds"])
