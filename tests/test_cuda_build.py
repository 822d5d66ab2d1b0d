"""Every Warp kernel the engine launches builds for a CUDA GPU, checked on a machine without one.

Warp's wheel carries NVRTC, so its ahead-of-time compiler turns each kernel module's CUDA
source into PTX for a given architecture with no GPU or driver present. The tests run the
kernels on the CPU device only; this is what catches CUDA-only build errors (native
snippets, 64-bit atomics, types the CPU compiler accepts and NVRTC does not) before a GPU
session spends its time on them. It says nothing about results on a GPU: those are
`tools/device_check.sh`'s job.
"""

from __future__ import annotations

import importlib
import json

import pytest
from _tools import load_tool

wp = pytest.importorskip("warp")

from perch_warp.kernels.features import feature_kernels  # noqa: E402

# sm_90: the H100/H200 machines the project's GPU figures come from.
ARCH = 90


KERNEL_MODULES = load_tool("cuda_resources").kernel_modules()


def _nvrtc_archs() -> list[int]:
    wp.init()
    try:
        return list(wp.get_cuda_supported_archs())
    except Exception:  # a Warp build without CUDA support
        return []


pytestmark = pytest.mark.skipif(
    ARCH not in _nvrtc_archs(), reason=f"this Warp build cannot compile CUDA for sm_{ARCH} (no NVRTC)"
)


def _ptx_entries(path) -> set[str]:
    text = path.read_bytes().decode("utf-8", errors="replace")
    return {line.split()[2].split("(")[0] for line in text.splitlines() if line.startswith(".visible .entry ")}


def _kernel_names(mod) -> set[str]:
    return {v.key for v in vars(mod).values() if isinstance(v, wp.Kernel)}


@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_kernel_module_compiles_to_ptx(name, tmp_path):
    mod = importlib.import_module(name)
    expected = _kernel_names(mod)
    assert expected, f"no kernels registered in {mod.__name__}"
    (ptx,) = wp.compile_aot_module(mod, arch=ARCH, module_dir=tmp_path, use_ptx=True)
    entries = _ptx_entries(ptx)
    # One forward entry per kernel: nothing was skipped as an unresolved generic.
    for key in expected:
        assert any(e.startswith(f"{key}_") and e.endswith("_cuda_kernel_forward") for e in entries), (key, entries)


def test_feature_kernels_compile_to_ptx(tmp_path):
    # Built per channel count, each in a module of its own ("unique"): compiled one by one.
    for kernel in feature_kernels(64)[1:]:
        (ptx,) = wp.compile_aot_module(kernel.module, arch=ARCH, module_dir=tmp_path, use_ptx=True)
        assert any(e.endswith("_cuda_kernel_forward") for e in _ptx_entries(ptx)), kernel.key


def test_kernel_modules_are_found():
    engine = {f"perch_warp.kernels.{m}" for m in ("bound", "boxes", "features", "raster", "reduce", "render")}
    beside_callers = {"perch_warp.photo_kernels", "perch_warp.bench.kernels"}  # the demo's and bench's own
    assert engine | beside_callers <= set(KERNEL_MODULES)


def test_occupancy_formula_reproduces_nsight_compute_on_the_h100():
    """Nsight Compute on an H100 (docs/performance.md) measured render_boxes at 71 registers per
    thread, theoretical occupancy 37.5 %, blocks of 256: the formula must give the same."""
    tool = load_tool("cuda_resources")
    assert tool.theoretical_occupancy(71, 256, 90) == (0.375, 3)
    assert tool.theoretical_occupancy(64, 256, 90) == (0.5, 4)  # 64 x 256 x 4 = the SM's 65,536 registers
    assert tool.theoretical_occupancy(16, 256, 90) == (1.0, 8)  # then threads per SM limit
    assert tool.theoretical_occupancy(16, 32, 90) == (0.5, 32)  # and blocks per SM


def test_cubin_registers_are_read_for_every_kernel(tmp_path):
    tool = load_tool("cuda_resources")
    mod = importlib.import_module("perch_warp.kernels.render")
    (cubin,) = wp.compile_aot_module(mod, arch=ARCH, module_dir=tmp_path, use_ptx=False)
    res = tool.cubin_resources(cubin)
    (entry,) = [k for k in res if k.startswith("render_boxes_")]
    # Nsight Compute read 71 on the H100 (Warp 1.19, CUDA 13); another NVRTC may allocate otherwise.
    assert 16 <= res[entry]["registers"] <= 255
    assert res[entry]["frame_bytes"] > 0  # the BVH traversal's stack lives in local memory
    assert tool.main(["--arch", "90", "--out", str(tmp_path / "r.json")]) == 0
    names = {r["kernel"] for r in json.loads((tmp_path / "r.json").read_text())["kernels"]}
    assert {"render_boxes", "splat_faces", "top_alpha_mean"} <= names
