"""The observed photo."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .errors import PerchError
from .outputs import atomic_write

# Photos larger than this are refused from their header, before any pixel is decoded: a 8000 x 6000
# photo (48 MP) already needs GBs once rendered and featurised, and a forged header claiming
# 100000 x 100000 must not be decoded at all. Resize such photos (and their intrinsics) first.
MAX_IMAGE_PIXELS = 50_000_000


def image_header_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from the image header without decoding pixels; PerchError naming the file when it is
    missing, unreadable or larger than MAX_IMAGE_PIXELS."""
    path = Path(path)
    if not path.is_file():
        raise PerchError(f"image not found: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # judged below, by our own limit
            with Image.open(path) as im:
                width, height = im.size
    except Image.DecompressionBombError:
        raise PerchError(f"image {path} claims an enormous size (a decompression bomb?): refused") from None
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise PerchError(f"cannot read image {path}: {e}") from None
    if width * height > MAX_IMAGE_PIXELS:
        raise PerchError(
            f"image {path} is {width}x{height} ({width * height / 1e6:.0f} MP), more than "
            f"{MAX_IMAGE_PIXELS / 1e6:.0f} MP: resize it (and scale cam_K alike)"
        )
    return width, height


def load_rgb(path: str | Path) -> np.ndarray:
    """An 8-bit RGB image (H, W, 3) uint8; greyscale/alpha are refused or dropped explicitly."""
    path = Path(path)
    image_header_size(path)  # size checked before decoding
    try:
        with Image.open(path) as im:
            mode = im.mode
            if mode in ("RGBA", "P", "RGB"):
                arr = np.asarray(im.convert("RGB"))
            else:
                raise PerchError(f"image {path} is {mode}, not RGB: the method needs colour")
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as e:
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
    """Write atomically so that an interrupted run leaves no half-written picture (nor a stray temporary)."""
    pic = Image.fromarray(np.asarray(rgb, dtype=np.uint8))
    atomic_write(path, lambda f: pic.save(f, format="PNG"))
