"""Where a bench figure comes from: the commit, the command, the device and peak memory."""

from __future__ import annotations

import os
import platform
import resource
import shlex
import subprocess
import sys
from pathlib import Path

import warp as wp

ENV_COMMIT = "PERCH_WARP_COMMIT"  # names the commit where the checkout's .git cannot


def git_commit(repo: Path | None = None) -> str:
    """`git rev-parse --short HEAD` of the checkout holding this package; 'unknown' outside one.

    $PERCH_WARP_COMMIT overrides it: a copy of a working tree on another machine (a lent
    GPU, say) may carry a `.git` that is not the code's, and its figures must name the right commit.
    """
    if os.environ.get(ENV_COMMIT):
        return os.environ[ENV_COMMIT]
    repo = repo or Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"


def git_dirty(repo: Path | None = None) -> bool | None:
    """Whether the checkout has uncommitted changes (figures then belong to no commit); None outside one
    or when $PERCH_WARP_COMMIT names the commit."""
    if os.environ.get(ENV_COMMIT):
        return None
    repo = repo or Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=repo,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return bool(out.stdout.strip()) if out.returncode == 0 else None


def command_line() -> str:
    """This process's command line as typed (`python -m perch_warp ...` for the module entry point)."""
    argv = list(sys.argv)
    head = ["python", "-m", "perch_warp"] if argv and argv[0].endswith("__main__.py") else argv[:1]
    return shlex.join(head + argv[1:])


def device_name(device: str) -> str:
    """A readable name: the GPU's, or the CPU model with its logical CPU count."""
    d = wp.get_device(device)
    if d.is_cuda:
        return f"{device}: {d.name}"
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"cpu: {model} ({os.cpu_count()} logical CPUs)"


def host_peak_mib() -> float:
    """Peak resident memory of this process so far (ru_maxrss), MiB."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1 << 20) if sys.platform == "darwin" else rss / 1024.0  # bytes on macOS, KiB on Linux


def device_peak_mib(device: str) -> tuple[float | None, str]:
    """High-water mark of Warp's CUDA memory pool on `device` (MiB) and what it is; None with the reason otherwise."""
    d = wp.get_device(device)
    if not d.is_cuda:
        return None, "n/a on the CPU"
    try:
        if not wp.is_mempool_enabled(d):
            return None, "n/a: Warp's CUDA memory pool is disabled on this device"
        return wp.get_mempool_used_mem_high(d) / (1 << 20), "peak of Warp's CUDA memory pool (since the process began)"
    except (RuntimeError, ValueError) as e:
        return None, f"n/a: {e}"
