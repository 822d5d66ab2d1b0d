"""Killing a command mid-run, for the resume tests (serial eval and eval --ray)."""

import os
import signal
import subprocess
import time
from pathlib import Path


def sigkill_once_written(proc: subprocess.Popen, path: Path, lines: int, timeout_s: float, group: bool = False) -> None:
    """Wait until `path` holds `lines` lines (or proc has ended, or timeout_s has passed), then SIGKILL proc and
    reap it; with `group`, also what is left of its process group (a proc started with start_new_session)."""
    try:
        deadline = time.time() + timeout_s
        while time.time() < deadline and proc.poll() is None:
            if path.exists() and path.read_text().count("\n") >= lines:
                break
            time.sleep(0.05)
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
        if group:
            try:  # the killed process's children in its session (e.g. the Ray processes it started)
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
