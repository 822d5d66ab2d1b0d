"""The observed photo."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import PerchError


def load_rgb(path: str | Path) -> np.ndarray:
    """An 8-bit RGB image (H, W, 3) uint8; greyscale/alpha are refused or dropped explicitly."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise PerchError(f"image not found: {path}")
    try:
        with Image.open(path) as im:
            mode = im.mode
            if mode in ("RGBA", "P", "RGB"):
                arr = np.asarray(im.convert("RGB"))
            else:
                raise PerchError(f"image {path} is {mode}, not RGB: the method needs colour")
    except (UnidentifiedImageError, OSError) as e:
        raise PerchError(f"cannot read image {path}: {e}") from None
    return check_rgb(arr, str(path))


def check_rgb(arr: np.ndarray, name: str = "image") -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise PerchError(f"{name} must be H x W x 3 RGB, got shape {arr.shape}")
    if arr.dtype != np.uint8:
        raise PerchError(f"{name} must be 8-bit (uint8), got {arr.dtype}")
    if arr.shape[0] < 16 or arr.shape[1] < 16:
        raise PerchError(f"{name} is too small ({arr.shape[1]}x{arr.shape[0]})")
    return np.ascontiguousarray(arr)


def save_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write atomically so that an interrupted run leaves no half-written picture."""
    import os

    from PIL import Image

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    Image.fromarray(np.asarray(rgb, dtype=np.uint8)).save(tmp, format="PNG")
    os.replace(tmp, path)
