"""Output files: checked before any work, written atomically, and an exclusive lock on an output folder.

Why: a search can take minutes to hours; an output path that cannot be written must be
refused before it starts, and an interrupted or failing write must leave neither a
half-written file nor a stray temporary one. Temporary names are unique (mkstemp), so two
processes writing the same file never trample each other's temporary.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

from .errors import PerchError

LOCK_FILE = ".perch_warp.lock"


def _existing_ancestor(path: Path) -> Path:
    """The nearest ancestor of `path` that exists (the folder a write would have to create folders in)."""
    p = path.parent
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output_file(path: str | Path, what: str) -> Path:
    """Refuse, before any work, an output file path that cannot be written: a folder, a path under a
    file, or an unwritable folder. Missing parent folders are fine (created at write time), so that
    a failing run leaves nothing behind."""
    path = Path(path)
    if path.is_dir():
        raise PerchError(f"{what} {path} is a folder: give a file name")
    anc = _existing_ancestor(path)
    if not anc.is_dir():
        raise PerchError(f"{what} {path} lies under {anc}, which is a file, not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise PerchError(f"{what} {path}: folder {anc} is not writable")
    if path.exists() and not os.access(path, os.W_OK):
        raise PerchError(f"{what} {path} exists and is not writable")
    return path


def check_output_dir(path: str | Path, what: str) -> Path:
    """Refuse an output folder that is a file, lies under a file, or cannot be written."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise PerchError(f"{what} {path} is a file, not a folder: give a folder")
    anc = path if path.is_dir() else _existing_ancestor(path)
    if not anc.is_dir():
        raise PerchError(f"{what} {path} lies under {anc}, which is a file, not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise PerchError(f"{what} {path}: folder {anc} is not writable")
    return path


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], None]) -> None:
    """Write `path` through `write(binary file)` into a uniquely named temporary beside it, fsync, rename.

    On any failure the temporary is removed and `path` keeps its old content (or stays absent).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # mkstemp creates 0600 files; give the result the mode a plain open() would (or the old file's).
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Remove the temporaries (`.NAME.*.tmp`) that atomic_write left in `folder` or below it (eval's
    heatmaps/) when its process was killed between mkstemp and rename; returns them. Only under the
    folder's lock (folder_lock): a live writer's temporary would otherwise go too."""
    stale = sorted(Path(folder).rglob(".*.tmp"))
    for tmp in stale:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    return stale


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode()))


@contextlib.contextmanager
def folder_lock(folder: str | Path, what: str = "output folder") -> Iterator[Path]:
    """Hold an exclusive lock on `folder` (flock on folder/.perch_warp.lock) for the block.

    A second process (or a second open in this one) is refused at once with the holder's pid.
    The lock dies with its process (kill -9 included), so a stale lock file never blocks a rerun.
    """
    import fcntl  # POSIX only: imported here so that this module (which every command imports) loads anywhere

    folder = Path(folder)
    lock_path = folder / LOCK_FILE
    f = open(lock_path, "a+")  # noqa: SIM115 - held open for the whole block
    try:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            f.seek(0)
            holder = f.read().strip() or "unknown"
            raise PerchError(
                f"{what} {folder} is in use by another run (pid {holder}): wait for it to finish or use another --out"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        yield folder
    finally:
        f.close()  # releases the lock
