"""Registers, local memory and theoretical occupancy of every Warp kernel on a CUDA GPU, without one.

    python tools/cuda_resources.py [--arch 90] [--block-dim 256] [--channels 96] [--out resources.json]

Warp's wheel carries NVRTC, which compiles each kernel module to a cubin for `--arch` here, GPU
or not (`wp.compile_aot_module`). The cubin's `.nv.info` sections record, per kernel, the
registers per thread and the per-thread stack frame (local memory: spills, arrays kept in local
memory, the BVH traversal stack of mesh queries) that ptxas settled on. From the registers and
Warp's launch block size follows the theoretical occupancy (resident warps per SM over the
maximum), the figure Nsight Compute's Occupancy section reports as theoretical: register use is
what limited kernel #1 (`render_boxes`: 71 registers, 37.5 % on an H100, docs/performance.md).
Nothing here is timed: whether fewer registers make a kernel faster is for a GPU to say.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import struct
import sys
import tempfile
from pathlib import Path

# Per-SM limits by compute capability (CUDA C Programming Guide, "Compute capabilities" table):
# max resident threads, max resident blocks, 32-bit registers.
SM_LIMITS = {
    75: (1024, 16, 65536),
    80: (2048, 32, 65536),
    86: (1536, 16, 65536),
    87: (1536, 16, 65536),
    89: (1536, 24, 65536),
    90: (2048, 32, 65536),
    100: (2048, 32, 65536),
}
REG_ALLOC_UNIT = 256  # registers are allocated per warp in units of 256 (8 per thread)

# .nv.info attribute codes (EIATTR_*) read here; each record is (format, attribute, u16) and, for
# format 4 (a sized value), that many bytes: (symbol index u32, value u32) for these three.
_EIATTR = {0x2F: "registers", 0x11: "frame_bytes", 0x23: "max_stack_bytes"}


def cubin_resources(path: Path) -> dict[str, dict[str, int]]:
    """Per kernel entry (`*_cuda_kernel_forward`) of a cubin: registers, frame and stack bytes."""
    b = Path(path).read_bytes()
    if b[:4] != b"\x7fELF" or b[4] != 2:
        raise ValueError(f"{path}: not a 64-bit ELF cubin")
    (shoff,) = struct.unpack_from("<Q", b, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", b, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", b, shoff + i * shentsize) for i in range(shnum)]

    def c_string(section: tuple, offset: int) -> str:
        start = section[4] + offset
        return b[start : b.index(b"\0", start)].decode()

    names = [c_string(sections[shstrndx], s[0]) for s in sections]
    symtab = next(s for s in sections if s[1] == 2)  # SHT_SYMTAB
    symbols = [
        c_string(sections[symtab[6]], struct.unpack_from("<I", b, symtab[4] + 24 * i)[0])
        for i in range(symtab[5] // 24)
    ]
    out: dict[str, dict[str, int]] = {}
    for name, s in zip(names, sections, strict=True):
        if not name.startswith(".nv.info"):
            continue
        p, end = s[4], s[4] + s[5]
        while p + 4 <= end:
            fmt, attr, value = struct.unpack_from("<BBH", b, p)
            p += 4
            if fmt != 4:
                continue
            if attr in _EIATTR and value >= 8:
                sym, v = struct.unpack_from("<II", b, p)
                out.setdefault(symbols[sym], {})[_EIATTR[attr]] = v
            p += value
    return {k: v for k, v in out.items() if k.endswith("_cuda_kernel_forward") and "registers" in v}


def theoretical_occupancy(registers: int, block_dim: int, arch: int) -> tuple[float, int]:
    """(resident warps / maximum, resident blocks per SM) for a kernel using `registers` per thread
    launched in blocks of block_dim threads, no shared memory, on compute capability `arch`."""
    max_threads, max_blocks, regs_per_sm = SM_LIMITS[arch]
    warps_per_block = math.ceil(block_dim / 32)
    regs_per_warp = math.ceil(max(registers, 1) * 32 / REG_ALLOC_UNIT) * REG_ALLOC_UNIT
    blocks = min(max_blocks, max_threads // block_dim, regs_per_sm // (regs_per_warp * warps_per_block))
    return blocks * warps_per_block / (max_threads // 32), blocks


# Kernel modules outside perch_warp.kernels: the demo's photographer and bench's microbenchmark keep
# their kernels beside their callers (the engine's are in perch_warp.kernels, found below).
OTHER_KERNEL_MODULES = ("perch_warp.photo_kernels", "perch_warp.bench.kernels")


def kernel_modules() -> list[str]:
    """Qualified names of the modules that define Warp kernels: every module of perch_warp.kernels
    (found, so a new one is not missed) and OTHER_KERNEL_MODULES."""
    import pkgutil

    import perch_warp.kernels
    import warp as wp

    names = []
    for info in pkgutil.iter_modules(perch_warp.kernels.__path__):
        name = f"perch_warp.kernels.{info.name}"
        if any(isinstance(v, wp.Kernel) for v in vars(importlib.import_module(name)).values()):
            names.append(name)
    return sorted(names) + list(OTHER_KERNEL_MODULES)


def compile_cubins(arch: int, channels: int, module_dir: Path) -> list[tuple[str, Path]]:
    """(module name, cubin) for every kernel module the engine launches, and the feature kernels
    built for `channels` (each in a module of its own)."""
    import warp as wp
    from perch_warp.kernels.features import feature_kernels

    out = []
    for name in kernel_modules():
        mod = importlib.import_module(name)
        (cubin,) = wp.compile_aot_module(mod, arch=arch, module_dir=module_dir, use_ptx=False)
        out.append((name, cubin))
    for kernel in feature_kernels(channels)[1:]:
        (cubin,) = wp.compile_aot_module(kernel.module, arch=arch, module_dir=module_dir, use_ptx=False)
        out.append((f"features (C={channels})", cubin))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arch", type=int, default=90, help="compute capability x 10 (default 90: H100/H200)")
    ap.add_argument("--block-dim", type=int, default=256, help="threads per block (default 256, Warp's launch default)")
    ap.add_argument(
        "--channels", type=int, default=96, help="conv1 channels of the feature kernels (default 96: Caffe)"
    )
    ap.add_argument("--out", type=Path, default=None, help="write the table here as JSON")
    args = ap.parse_args(argv)
    if args.arch not in SM_LIMITS:
        print(f"cuda_resources: --arch {args.arch} not known here (known: {sorted(SM_LIMITS)})", file=sys.stderr)
        return 1
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    wp.init()
    if args.arch not in wp.get_cuda_supported_archs():
        print(
            f"cuda_resources: this Warp build cannot compile for sm_{args.arch} (NVRTC archs: "
            f"{wp.get_cuda_supported_archs()})",
            file=sys.stderr,
        )
        return 1
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for module, cubin in compile_cubins(args.arch, args.channels, Path(tmp)):
            for entry, res in sorted(cubin_resources(cubin).items()):
                kernel = entry.removesuffix("_cuda_kernel_forward").rsplit("_", 1)[0]
                occupancy, blocks = theoretical_occupancy(res["registers"], args.block_dim, args.arch)
                rows.append(
                    {"module": module, "kernel": kernel, **res, "occupancy": occupancy, "blocks_per_sm": blocks}
                )
    print(
        f"sm_{args.arch}, {args.block_dim} threads per block, NVRTC {'.'.join(map(str, wp.get_cuda_toolkit_version()))}"
    )
    print(f"{'kernel':<46} {'regs':>5} {'frame B':>8} {'occupancy':>10}")
    for r in rows:
        print(f"{r['kernel']:<46} {r['registers']:>5} {r.get('frame_bytes', 0):>8} {r['occupancy']:>9.1%}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        report = {"arch": args.arch, "block_dim": args.block_dim, "channels": args.channels, "kernels": rows}
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
