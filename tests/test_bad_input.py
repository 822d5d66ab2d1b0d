"""Issue 18's catalogue of hostile-but-fair input, table-driven, with the ok cases beside them.

Every bad case must end with exit code 1, exactly one line on stderr that names the culprit, no
traceback, and nothing written where the outputs were to go. Each was checked to fail on the code
before issue 18 (a traceback, a silent exit 0, or a message that does not name the culprit).
The single-image cases use the demo's scene (written here, no ../shared needed); the eval cases use
test_bop's tiny dataset with a fake estimator, so no case runs a real search except the ok runs.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_bop import write_tiny_dataset
from test_evaluate import FakeEstimator

from perch_warp.cli import main
from perch_warp.demo import demo_scene, write_scene
from perch_warp.eval import command

TINY = ["--device", "cpu", "--yaw-step", "30", "--no-refine", "--quiet"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("scene")
    write_scene(demo_scene(seed=2), d)
    return d


def _png_header(path: Path, width: int, height: int) -> Path:
    """A PNG whose header claims width x height (the pixels are never there: a decompression bomb)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", b"") + chunk(b"IEND", b""))
    return path


def _edit_json(src: Path, dst: Path, edit: Callable[[dict], object]) -> Path:
    data = json.loads(src.read_text())
    out = edit(data)
    dst.write_text(json.dumps(data if out is None else out))
    return dst


def _gt_edit(key: str, value) -> Callable[[dict], None]:
    def edit(d: dict) -> None:
        d["1"][0][key] = value

    return edit


def _rotation_scaled(factor: float) -> Callable[[dict], None]:
    def edit(d: dict) -> None:
        d["1"][0]["cam_R_m2c"] = (np.asarray(d["1"][0]["cam_R_m2c"]) * factor).tolist()

    return edit


def _cam_edit(key: str, value) -> Callable[[dict], None]:
    def edit(d: dict) -> None:
        if value is KeyError:
            del d["1"][key]
        else:
            d["1"][key] = value

    return edit


def _mesh_without(scene: Path, tmp: Path, drop: str) -> Path:
    """The demo mesh copied with one of its files (.mtl or .png) left out."""
    m = tmp / "m"
    m.mkdir()
    for suffix in (".obj", ".mtl", ".png"):
        if suffix != drop:
            (m / f"obj_000001{suffix}").write_bytes((scene / "models" / f"obj_000001{suffix}").read_bytes())
    return m / "obj_000001.obj"


def _resized(scene: Path, tmp: Path, factor: int) -> Path:
    im = Image.open(scene / "rgb" / "000001.png")
    im.resize((im.width * factor, im.height * factor)).save(tmp / "000001.png")
    return tmp / "000001.png"


# (case id, how to build (scene, tmp) -> {"image"|"mesh"|"camera"|"truth": path, "extra": [...]}, culprit)
# The culprit is a piece of the one line that names the file or value and what is wrong with it.
BAD_ESTIMATE: list[tuple[str, Callable[[Path, Path], dict], str]] = [
    # 1. missing material file or texture: refused, never searched in a placeholder colour
    ("mtl missing", lambda s, t: {"mesh": _mesh_without(s, t, ".mtl")}, "obj_000001.mtl (mtllib) is missing"),
    ("map_Kd missing", lambda s, t: {"mesh": _mesh_without(s, t, ".png")}, "obj_000001.png (map_Kd in"),
    # 2. image size against the intrinsics
    ("image 2x the intrinsics", lambda s, t: {"image": _resized(s, t, 2)}, "principal point"),
    ("forged 64 MP header", lambda s, t: {"image": _png_header(t / "000001.png", 8000, 8000)}, "8000x8000 (64 MP)"),
    # 10. decompression bomb
    ("bomb header", lambda s, t: {"image": _png_header(t / "000001.png", 100000, 100000)}, "decompression bomb"),
    # 3. search size: refused up front with the count and the memory
    (
        "table 100 m wide",
        lambda s, t: {"extra": ["--x-range", "-50", "50", "--y-range", "-50", "50"]},
        "candidates (x -50..50 m",
    ),
    ("xy step 1e-6", lambda s, t: {"extra": ["--xy-step", "1e-6"]}, "--max-candidates 50,000,000"),
    ("max-candidates 100", lambda s, t: {"extra": ["--max-candidates", "100"]}, "more than --max-candidates 100"),
    ("max-candidates 0", lambda s, t: {"extra": ["--max-candidates", "0"]}, "--max-candidates must be at least 1"),
    # 10. option values
    ("xy step 0", lambda s, t: {"extra": ["--xy-step", "0"]}, "--xy-step must be a positive finite number, got 0"),
    ("batch pixels 0", lambda s, t: {"extra": ["--batch-pixels", "0"]}, "--batch-pixels must be a positive"),
    ("batch pixels -5", lambda s, t: {"extra": ["--batch-pixels", "-5"]}, "got -5"),
    ("stride 1000", lambda s, t: {"extra": ["--stride", "1000"]}, "--stride must be 1..32 pixels, got 1000"),
    ("refine peaks 0", lambda s, t: {"extra": ["--refine-peaks", "0"]}, "--refine-peaks) must be at least 1, got 0"),
    ("refine yaws 0", lambda s, t: {"extra": ["--refine-yaws", "0"]}, "--refine-yaws) must be at least 1, got 0"),
    ("unknown score term", lambda s, t: {"extra": ["--score", "colour=red"]}, "unknown score term 'colour'"),
    ("yaw step nan", lambda s, t: {"extra": ["--yaw-step", "nan"]}, "--yaw-step must be a positive finite"),
    # 4. output paths, before the search
    ("--out is a folder", lambda s, t: {"out": t / "outdir", "mkdir": t / "outdir"}, "is a folder: give a file"),
    ("--overlay under a file", lambda s, t: {"overlay": t / "f" / "o.png", "touch": t / "f"}, "which is a file"),
    (
        "--heatmap is a folder",
        lambda s, t: {"extra": ["--heatmap", str(t / "outdir")], "mkdir": t / "outdir"},
        "--heatmap",
    ),  # fmt: skip
    # 7. --truth through the one validated BOP reader
    (
        "truth top-level list",
        lambda s, t: {"truth": _edit_json(s / "scene_gt.json", t / "gt.json", lambda d: [d])},
        "must hold a JSON object keyed by integer ids",
    ),  # fmt: skip
    (
        "truth no cam_R_m2c",
        lambda s, t: {
            "truth": _edit_json(s / "scene_gt.json", t / "gt.json", lambda d: d["1"][0].pop("cam_R_m2c") and None)
        },
        "needs obj_id, cam_R_m2c and cam_t_m2c",
    ),  # fmt: skip
    (
        "truth obj_id nine",
        lambda s, t: {"truth": _edit_json(s / "scene_gt.json", t / "gt.json", _gt_edit("obj_id", "nine"))},
        "obj_id 'nine' is not an integer",
    ),  # fmt: skip
    (
        "truth 2-number t",
        lambda s, t: {"truth": _edit_json(s / "scene_gt.json", t / "gt.json", _gt_edit("cam_t_m2c", [1.0, 2.0]))},
        "cam_t_m2c (mm) must be 3 finite numbers",
    ),  # fmt: skip
    # 8. a rotation beyond the SO(3) projection's tolerance
    (
        "truth not a rotation",
        lambda s, t: {"truth": _edit_json(s / "scene_gt.json", t / "gt.json", _rotation_scaled(1.1))},
        "cam_R_m2c is not a rotation (max |R R^T - I| = 0.21 > 0.02)",
    ),  # fmt: skip
    ("obj-id without truth", lambda s, t: {"extra": ["--obj-id", "1"], "truth": None}, "--obj-id needs --truth"),
    # 10. camera width/height that are not numbers
    (
        "camera width abc",
        lambda s, t: {"camera": _edit_json(s / "scene_camera.json", t / "c.json", _cam_edit("width", "abc"))},
        "'width' must be a positive whole number of pixels, got 'abc'",
    ),  # fmt: skip
    (
        "camera height null",
        lambda s, t: {"camera": _edit_json(s / "scene_camera.json", t / "c.json", _cam_edit("height", None))},
        "'height' must be a positive whole number of pixels, got None",
    ),  # fmt: skip
    # 9. messages that name the real culprit
    (
        "no table frame",
        lambda s, t: {"camera": _edit_json(s / "scene_camera.json", t / "c.json", _cam_edit("cam_R_w2c", KeyError))},
        "add them to the camera file (or, for a BOP dataset",
    ),  # fmt: skip (not the nonexistent --table)
    ("mesh units wrong", lambda s, t: {"extra": ["--mesh-units", "mm"]}, "read as mm (given)"),
    # several objects (issue 19 part 2)
    (
        "--mesh and --models",
        lambda s, t: {"extra": ["--models", str(s / "models"), "--objects", "1"]},
        "give either --mesh or --models DIR --objects ID ..., not both",
    ),  # fmt: skip
    (
        "--objects 7 has no mesh",
        lambda s, t: {"mesh": None, "extra": ["--models", str(s / "models"), "--objects", "7"]},
        "--objects 7: no mesh",
    ),  # fmt: skip
    ("--objects without --models", lambda s, t: {"mesh": None, "extra": ["--objects", "1"]}, "go together"),
    (
        "several with --obj-id",
        lambda s, t: {"truth": s / "scene_gt.json", "extra": ["--mesh", str(s / "models" / "obj_000001.obj")]},
        "--obj-id names one object",
    ),  # fmt: skip
    (
        "several with --no-refine",
        lambda s, t: {"extra": ["--mesh", str(s / "models" / "obj_000001.obj")]},
        "several objects need their peaks refined: drop --no-refine",
    ),  # fmt: skip
    (
        "joint peaks 0",
        lambda s, t: {"extra": ["--mesh", str(s / "models" / "obj_000001.obj"), "--joint-peaks", "0"]},
        "--joint-peaks must be at least 1, got 0",
    ),  # fmt: skip
]


def _estimate_args(scene: Path, tmp: Path, spec: dict) -> list[str]:
    if "mkdir" in spec:
        spec["mkdir"].mkdir()
    if "touch" in spec:
        spec["touch"].write_text("")
    out = spec.get("out", tmp / "out" / "sub" / "r.json")
    overlay = spec.get("overlay", tmp / "out" / "sub" / "o.png")
    mesh = spec.get("mesh", scene / "models" / "obj_000001.obj")
    args = [
        str(spec.get("image", scene / "rgb" / "000001.png")),
        *(["--mesh", str(mesh)] if mesh is not None else []),
        "--camera",
        str(spec.get("camera", scene / "scene_camera.json")),
        "--out",
        str(out),
        "--overlay",
        str(overlay),
        *TINY,
        *spec.get("extra", []),
    ]
    truth = spec.get("truth", False)
    if truth:
        args += ["--truth", str(truth), "--obj-id", "1"]
    return args


def _one_line_error(capsys, code: int) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 1, captured.err
    assert "Traceback" not in captured.err + captured.out
    assert len(lines) == 1 and lines[0].startswith("perch_warp: error: "), lines
    return lines[0]


def _left_behind(tmp: Path) -> list[str]:
    """Files the run left in its output folders (and any temporary anywhere under tmp)."""
    left = [str(p) for p in (tmp / "out").rglob("*")] if (tmp / "out").exists() else []
    left += [str(p) for p in tmp.rglob("*.tmp")]
    for d in ("outdir",):
        if (tmp / d).exists():
            left += [str(p) for p in (tmp / d).rglob("*")]
    return left


@pytest.mark.parametrize("case", BAD_ESTIMATE, ids=[c[0] for c in BAD_ESTIMATE])
def test_bad_estimate_input_is_one_line_naming_the_culprit(case, scene, tmp_path, capsys):
    _, build, culprit = case
    args = _estimate_args(scene, tmp_path, build(scene, tmp_path))
    code = main(args)
    line = _one_line_error(capsys, code)
    assert culprit in line, line
    assert _left_behind(tmp_path) == []


def test_ok_estimate_beside_the_bad_cases(scene, tmp_path, capsys):
    """The same scene with a near-orthonormal ground truth (off by 3e-3, as public BOP files are), outputs in a
    folder that does not exist yet: exit 0, both outputs complete, no temporary left."""
    truth = _edit_json(scene / "scene_gt.json", tmp_path / "gt.json", _rotation_scaled(1.003))
    sc = demo_scene(seed=2)
    gx, gy, _ = sc.truth_xy_yaw
    x, y = round(gx, 2), round(gy, 2)
    spec = {
        "truth": truth,
        "extra": ["--x-range", f"{x - 0.02}", f"{x + 0.02}", "--y-range", f"{y - 0.02}", f"{y + 0.02}"],
    }
    code = main(_estimate_args(scene, tmp_path, spec))
    captured = capsys.readouterr()
    assert code == 0, captured.err
    res = json.loads((tmp_path / "out" / "sub" / "r.json").read_text())
    assert res["truth"]["adds_m"] < 0.03
    assert Image.open(tmp_path / "out" / "sub" / "o.png").size[0] == sc.camera.width  # (plus a caption below)
    assert sorted(p.name for p in (tmp_path / "out" / "sub").iterdir()) == ["o.png", "r.json"]


# ----------------------------------------------------------------------------- eval


@pytest.fixture()
def tiny(tmp_path, monkeypatch):
    root = write_tiny_dataset(tmp_path / "ds")
    est = FakeEstimator()
    monkeypatch.setattr(command, "EngineEstimator", lambda *a, **k: est)
    return root, est


def _eval(root: Path, out: Path, *extra: str) -> int:
    return main(["eval", "--dataset", str(root), "--out", str(out), "--no-plots", "--xy-step", "0.02", *extra])


def test_eval_out_that_is_a_file_is_refused_before_any_work(tiny, tmp_path, capsys):
    root, est = tiny
    (tmp_path / "f").write_text("x")
    line = _one_line_error(capsys, _eval(root, tmp_path / "f"))
    assert "--out" in line and "is a file, not a folder" in line and est.calls == []
    line = _one_line_error(capsys, _eval(root, tmp_path / "f" / "sub"))
    assert "lies under" in line and str(tmp_path / "f") in line


def test_eval_bad_options_leave_no_outdir(tiny, tmp_path, capsys):
    root, est = tiny
    for bad, culprit in ((["--batch-pixels", "0"], "--batch-pixels"), (["--xy-step", "0"], "--xy-step")):
        line = _one_line_error(capsys, _eval(root, tmp_path / "out", *bad))
        assert culprit in line
    assert not (tmp_path / "out").exists() and est.calls == []


def test_eval_scene_folders_2_and_superscript_do_not_count_or_crash(tiny, tmp_path, capsys):
    """A stray folder `2` beside `000001`..., and one named `²` (str.isdigit accepts it; int() does not)."""
    root, est = tiny
    (root / "test" / "1").mkdir()  # would be read back as 000001: scene 1 twice
    (root / "test" / "²").mkdir()
    assert _eval(root, tmp_path / "out") == 0, capsys.readouterr().err
    assert len(est.calls) == 5 == len(set(est.calls))
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["n_targets"] == 5


def test_eval_bad_target_is_recorded_and_the_others_finish(tiny, tmp_path, capsys):
    """Item 8: a rotation beyond the tolerance fails its target only (exit 1); a near-orthonormal one is
    projected and counted."""
    root, est = tiny
    gt = root / "test" / "000001" / "scene_gt.json"
    data = json.loads(gt.read_text())
    data["1"][1]["cam_R_m2c"] = (np.asarray(data["1"][1]["cam_R_m2c"]) * 1.3).tolist()  # target (1, 1, 1)
    data["2"][0]["cam_R_m2c"] = (np.asarray(data["2"][0]["cam_R_m2c"]) * 1.004).tolist()  # (1, 2, 0): projected
    gt.write_text(json.dumps(data))
    code = _eval(root, tmp_path / "out")
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and "1 of 5 targets failed" in err
    assert sorted(est.calls) == [(1, 1, 0), (1, 1, 3), (1, 2, 0), (1, 2, 1)]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["n_failed"] == 1 and summary["n_evaluated"] == 4 and summary["n_gt_rotations_projected"] == 1
    assert "cam_R_m2c is not a rotation" in summary["failed"][0]["reason"]
    rows = (tmp_path / "out" / "per_target.csv").read_text().splitlines()
    assert len(rows) == 6 and rows[-1].startswith("1,1,1,1,") and "not a rotation" in rows[-1]
    journal = [json.loads(x) for x in (tmp_path / "out" / "targets.jsonl").read_text().splitlines()]
    assert [j for j in journal if "failed" in j][0]["inst"] == 1
    assert "FAILED: 1 targets" in (tmp_path / "out" / "table.txt").read_text()
