"""Where the project's external data lives (never committed: found at run time)."""

from __future__ import annotations

import os
from pathlib import Path

ENV_SHARED = "PERCH_WARP_SHARED"


def shared_dir() -> Path | None:
    """The `shared/` data folder: $PERCH_WARP_SHARED, else `../shared` beside the repository or the cwd."""
    env = os.environ.get(ENV_SHARED)
    if env:
        return Path(env) if Path(env).is_dir() else None
    here = Path(__file__).resolve().parent.parent
    for cand in (here.parent / "shared", Path.cwd().parent / "shared", Path.cwd() / "shared"):
        if (cand / "README.md").is_file():
            return cand
    return None


def shared_file(*parts: str) -> Path | None:
    """A file under `shared/`, or None when shared/ or the file is absent."""
    root = shared_dir()
    if root is None:
        return None
    p = root.joinpath(*parts)
    return p if p.exists() else None
