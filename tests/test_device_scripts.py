"""tools/stage_data_for_device.sh and tools/device_accuracy.sh (issue 17's test runs on a GPU): the staged
folder holds what `eval` reads and nothing else, in the shared folder's layout; bad input is refused
with a one-line error and leaves nothing behind. The GPU run itself is not tested here (no GPU in CI)."""

import os
import subprocess
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def _touch(path: Path, text: str = "x") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


@pytest.fixture
def repo(tmp_path):
    """A git checkout to stage into, a synthetic set and a shared folder (file names as the real ones)."""
    root = tmp_path / "repo"
    root.mkdir()
    subprocess.run(["git", "init", "-q", str(root)], check=True)
    synth = tmp_path / "synth"
    scene = synth / "test" / "000001"
    for name in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json"):
        _touch(scene / name, "{}")
    _touch(scene / "rgb" / "000001.png")
    _touch(scene / "depth" / "000001.png")
    _touch(scene / "mask_visib" / "000001_000000.png")
    _touch(synth / "dataset_info.json", '{"models_dir": "/somewhere/else"}')
    _touch(synth / "camera.json", "{}")
    shared = tmp_path / "shared"
    for o in range(1, 10):
        for ext in ("obj", "mtl", "png"):
            _touch(shared / "data" / "ycbv" / "models" / f"obj_{o:06d}.{ext}")
    _touch(shared / "data" / "ycbv" / "test" / "000048" / "rgb" / "000001.png")
    _touch(shared / "data" / "ycbv" / "test" / "000048" / "scene_gt.json", "{}")
    _touch(shared / "weights" / "bvlc_alexnet_conv1.npz")
    return root, synth, shared


def _run(script: str, *args, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    full = {k: v for k, v in os.environ.items() if k not in ("PERCH_WARP_COMMIT", "PERCH_WARP_SHARED")}
    full.update(env or {})
    return subprocess.run(
        ["bash", str(TOOLS / script), *map(str, args)], cwd=cwd, env=full, capture_output=True, text=True
    )


def test_stage_copies_what_eval_reads_in_the_shared_layout(repo):
    root, synth, shared = repo
    r = _run("stage_data_for_device.sh", synth, shared, cwd=root)
    assert r.returncode == 0, r.stderr
    d = root / ".devdata"
    assert (d / "synth_ycbv" / "test" / "000001" / "rgb" / "000001.png").is_file()
    assert (d / "synth_ycbv" / "test" / "000001" / "scene_gt_info.json").is_file()
    assert (d / "synth_ycbv" / "camera.json").is_file()
    # the table comes from cam_R_w2c: depth and masks stay behind, and so does the absolute models_dir
    assert not (d / "synth_ycbv" / "test" / "000001" / "depth").exists()
    assert not (d / "synth_ycbv" / "test" / "000001" / "mask_visib").exists()
    assert not (d / "synth_ycbv" / "dataset_info.json").exists()
    assert (d / "data" / "ycbv" / "test" / "000048" / "scene_gt.json").is_file()
    objs = sorted(int(p.stem[4:]) for p in (d / "data" / "ycbv" / "models").glob("obj_*.obj"))
    assert objs == [1, 3, 4, 5, 6, 8, 9]
    assert (d / "weights" / "bvlc_alexnet_conv1.npz").is_file()
    assert "/.devdata/" in (root / ".git" / "info" / "exclude").read_text().split()
    assert not list(root.glob(".devdata.*"))  # no temporary left


def test_stage_refuses_a_folder_that_is_not_a_set_and_leaves_nothing(repo, tmp_path):
    root, _, shared = repo
    r = _run("stage_data_for_device.sh", tmp_path / "nothing", shared, cwd=root)
    assert r.returncode == 2
    assert "nothing is not a synthetic BOP set" in r.stderr and r.stderr.count("\n") == 1
    assert not list(root.glob(".devdata*"))


def test_accuracy_run_refuses_bad_input_with_one_line(repo):
    root, synth, shared = repo
    r = _run("device_accuracy.sh", "synth", cwd=root)
    assert r.returncode == 2 and "set PERCH_WARP_COMMIT" in r.stderr
    r = _run("device_accuracy.sh", "synth", cwd=root, env={"PERCH_WARP_COMMIT": "abc"})
    assert r.returncode == 2 and "run tools/stage_data_for_device.sh" in r.stderr
    assert _run("stage_data_for_device.sh", synth, shared, cwd=root).returncode == 0
    r = _run("device_accuracy.sh", "both", cwd=root, env={"PERCH_WARP_COMMIT": "abc"})
    assert r.returncode == 2 and "must be synth or real, got 'both'" in r.stderr and r.stderr.count("\n") == 1
