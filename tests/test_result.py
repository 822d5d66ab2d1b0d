"""Result and SearchInfo: the --out JSON keeps its keys, order and values (a user-facing format)."""

import numpy as np

from perch_warp.result import Candidate, Result, SearchInfo

# The result JSON's top level as written before SearchInfo existed (engine.py's info dict), in order,
# and the confidence (issue 19) appended after them.
KEYS = [
    "pose",
    "top_k",
    "n_candidates",
    "n_scored",
    "timings_s",
    "device",
    "weights",
    "stride_px",
    "alpha",
    "clusters",
    "seed",
    "score",
    "search",
    "search_option",
    "renderer_option",
    "mesh_faces",
    "median_box_px",
    "renderer",
    "cull_back_faces",
    "conv",
    "conv_option",
    "image_scale",
    "search_space",
    "evaluated",
    "batches",
    "rays",
    "threads",
    "bounded",
    "scored",
    "refine",
    "confidence",
]


def _info(**kw) -> SearchInfo:
    fields = dict(
        weights="random test filters",
        stride_px=4,
        alpha=0.5,
        clusters=20,
        seed=0,
        score="thesis",
        search="pruned",
        search_option="auto",
        renderer_option="auto",
        mesh_faces=12,
        median_box_px=4436.0,
        renderer="raster",
        cull_back_faces=True,
        conv="torch",
        conv_option="auto",
        image_scale=1.0,
        search_space="x -0.1..+0.1 m",
        evaluated=7,
        batches=2,
        rays=1234,
        threads=2,
        extra={"bounded": 9, "scored": 7, "refine": {"score_gain": 0.01}},
    )
    return SearchInfo(**{**fields, **kw})


def _result(info: SearchInfo) -> Result:
    c = Candidate(0.01, -0.02, 0.5, 0.9, np.eye(4))
    return Result(c, [c], 9, 7, {"total": 1.0}, "cpu", info)


def test_result_json_keeps_the_keys_and_their_order():
    d = _result(_info()).to_dict()
    assert list(d) == KEYS
    assert d["renderer"] == "raster" and d["median_box_px"] == 4436.0 and d["bounded"] == 9
    assert d["refine"] == {"score_gain": 0.01} and d["threads"] == 2


def test_median_box_is_written_only_where_the_auto_rule_ran():
    d = _result(_info(median_box_px=None, renderer_option="bvh")).to_dict()
    assert list(d) == [k for k in KEYS if k != "median_box_px"]


def test_search_info_round_trips_through_its_json():
    for info in (_info(), _info(median_box_px=None, extra={})):
        d = _result(info).to_dict()
        assert SearchInfo.from_dict(d) == info
        assert _result(SearchInfo.from_dict(d)).to_dict() == d
