"""tools/scaling.py on a tiny sweep of the real frame: every point searched, its rays and renderer recorded."""

import json

from _device import DEVICE
from _tools import load_tool


def test_image_scale_sweep_records_rays_and_renderer(shared, tmp_path):
    tool = load_tool("scaling")
    args = ["--dataset", str(shared / "data" / "ycbv"), "--device", DEVICE, "--yaw-step", "1.5"]
    args += ["--base-clip", "0.05", "--base-xy", "0.04", "--base-scale", "0.25", "--clips", "0.05"]
    args += ["--xy-steps", "0.04", "--scales", "0.25", "0.5", "--out", str(tmp_path)]
    assert tool.main(args) == 0
    r = json.loads((tmp_path / "scaling.json").read_text())
    assert (tmp_path / "scaling.png").stat().st_size > 0
    by_scale = {p["image_scale"]: p for p in r["points"]}
    assert set(by_scale) == {0.25, 0.5}
    for p in by_scale.values():
        assert p["evaluated"] == p["candidates"] > 0 and p["rays"] > 0 and p["search_s"] > 0
        assert p["renderer"] in ("bvh", "raster") and p["threads"] >= 1
    # The same poses at twice the image size: the candidates' boxes cover about 4x the pixels.
    assert by_scale[0.5]["candidates"] == by_scale[0.25]["candidates"]
    assert 3.0 < by_scale[0.5]["rays"] / by_scale[0.25]["rays"] < 5.0
