"""Feature weights: the first convolution of an ImageNet-pretrained AlexNet.

Sources (`load_feature_weights(spec)`):
- "torchvision": torchvision's AlexNet conv1 (64 filters) through
  `torch.hub.load_state_dict_from_url` (cached by torch, plus a small extract here);
- "caffe": the original BVLC Caffe AlexNet conv1 (96 filters) from
  `shared/weights/bvlc_alexnet_conv1.npz` (or $PERCH_WARP_WEIGHTS);
- a path to an .npz with `weight` (C, 3, k, k) OIHW over RGB, `bias` (C,), and the
  preprocessing as `mean`/`std` (3,) for RGB in [0, 1] or `preprocessing` = "caffe" |
  "torchvision";
- "auto": caffe when that file is present, else torchvision (cache, then download).
  Whatever is chosen is named in `FeatureWeights.source`; nothing is swapped silently.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from .errors import PerchError
from .paths import shared_file

TORCHVISION_ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
CAFFE_MEAN_255 = (123.68, 116.78, 103.94)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
PREPROCESSING = {
    # Caffe: RGB 0..255 minus the ImageNet mean, i.e. (rgb01 - mean/255) / (1/255).
    "caffe": (tuple(m / 255.0 for m in CAFFE_MEAN_255), (1 / 255.0,) * 3),
    "torchvision": (IMAGENET_MEAN, IMAGENET_STD),
}
HOW_TO_PROVIDE = (
    "provide conv1 weights with --weights FILE.npz (keys weight (C,3,k,k) RGB, bias, preprocessing), "
    "put the Caffe file at shared/weights/bvlc_alexnet_conv1.npz or set PERCH_WARP_WEIGHTS, "
    "or allow the torchvision download (needs internet once)"
)


@dataclass(frozen=True)
class FeatureWeights:
    """Conv1 weights (C, 3, k, k) over RGB with the preprocessing they expect on RGB in [0, 1]."""

    weight: np.ndarray
    bias: np.ndarray
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    source: str

    @property
    def channels(self) -> int:
        return int(self.weight.shape[0])

    @property
    def kernel_size(self) -> int:
        return int(self.weight.shape[2])

    def folded(self) -> tuple[np.ndarray, np.ndarray]:
        """(Wt, b): tap-major weights ((k*k*3), C) and bias that act on RGB in [0, 1] directly.

        conv((x - mean) / std) = conv'(x) with W' = W / std and b' = b - sum(W * mean / std),
        which saves normalising every rendered pixel.
        """
        mean = np.asarray(self.mean, np.float64)[None, :, None, None]
        std = np.asarray(self.std, np.float64)[None, :, None, None]
        W = self.weight.astype(np.float64) / std
        b = self.bias.astype(np.float64) - (W * mean).sum(axis=(1, 2, 3))
        Wt = W.transpose(2, 3, 1, 0).reshape(-1, self.channels)  # (dy, dx, ch_in) x C
        return np.ascontiguousarray(Wt, np.float32), b.astype(np.float32)


def smoothed(w: FeatureWeights, sigma_px: float) -> FeatureWeights:
    """w with every filter low-passed: each (output, input channel) k x k plane convolved with a
    Gaussian of sigma_px pixels, kept at k x k (zero beyond it, the Gaussian's taps out to k - 1), the
    bias as it is (the score term `smooth`, perch_warp.score_terms). conv1 with these reads a window as
    conv1 reads it blurred, so pixel noise and texture finer than sigma no longer move the features."""
    if sigma_px <= 0.0:
        return w
    k = w.kernel_size
    planes = ndimage.gaussian_filter(
        w.weight.astype(np.float64), (0.0, 0.0, sigma_px, sigma_px), mode="constant", truncate=(k - 1) / sigma_px
    )
    return dataclasses.replace(
        w, weight=planes.astype(np.float32), source=f"{w.source}, low-passed (Gaussian sigma {sigma_px} px)"
    )


def _validate(weight, bias, source: str) -> tuple[np.ndarray, np.ndarray]:
    weight = np.asarray(weight, dtype=np.float32)
    bias = np.asarray(bias, dtype=np.float32)
    if weight.ndim != 4 or weight.shape[1] != 3 or weight.shape[2] != weight.shape[3] or weight.shape[2] % 2 == 0:
        raise PerchError(f"{source}: weight must be (C, 3, k, k) with odd k, got {weight.shape}")
    if bias.shape != (weight.shape[0],):
        raise PerchError(f"{source}: bias must be ({weight.shape[0]},), got {bias.shape}")
    if not (np.all(np.isfinite(weight)) and np.all(np.isfinite(bias))):
        raise PerchError(f"{source}: weights contain NaN or infinity")
    return weight, bias


def load_npz(path: str | Path, preprocessing: str | None = None) -> FeatureWeights:
    path = Path(path)
    if not path.is_file():
        raise PerchError(f"weights file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as d:
            data = {k: d[k] for k in d.files}
    except (OSError, ValueError) as e:
        raise PerchError(f"cannot read weights {path}: {e}") from None
    if "weight" not in data or "bias" not in data:
        raise PerchError(f"weights {path} need keys 'weight' and 'bias', has {sorted(data)}")
    weight, bias = _validate(data["weight"], data["bias"], str(path))
    if "mean" in data and "std" in data:
        mean = tuple(float(x) for x in np.asarray(data["mean"]).reshape(3))
        std = tuple(float(x) for x in np.asarray(data["std"]).reshape(3))
        prep = "mean/std from file"
    else:
        prep = preprocessing or (str(data["preprocessing"]) if "preprocessing" in data else None)
        if prep not in PREPROCESSING:
            raise PerchError(
                f"weights {path}: say which preprocessing they expect (key 'preprocessing' = caffe|torchvision, "
                "or 'mean'/'std' for RGB in [0, 1])"
            )
        mean, std = PREPROCESSING[prep]
    if min(std) <= 0:
        raise PerchError(f"weights {path}: std must be positive, got {std}")
    return FeatureWeights(weight, bias, mean, std, f"{path} ({weight.shape[0]} filters, {prep} preprocessing)")


def caffe_weights_path() -> Path | None:
    env = os.environ.get("PERCH_WARP_WEIGHTS")
    if env:
        return Path(env)
    return shared_file("weights", "bvlc_alexnet_conv1.npz")


def load_caffe() -> FeatureWeights:
    path = caffe_weights_path()
    if path is None:
        raise PerchError(
            "Caffe AlexNet conv1 weights not found (shared/weights/bvlc_alexnet_conv1.npz); " + HOW_TO_PROVIDE
        )
    w = load_npz(path, preprocessing="caffe")
    return FeatureWeights(w.weight, w.bias, w.mean, w.std, f"Caffe BVLC AlexNet conv1: {w.source}")


def _torchvision_cache() -> Path:
    import torch.hub  # torch (seconds to import) only for the torchvision weights, here and below

    return Path(torch.hub.get_dir()) / "perch_warp" / "alexnet_conv1_torchvision.npz"


def load_torchvision(download: bool = True) -> FeatureWeights:
    """torchvision's ImageNet AlexNet conv1 (`features.0`), downloading the checkpoint once."""
    cache = _torchvision_cache()
    if cache.is_file():
        w = load_npz(cache, preprocessing="torchvision")
        return FeatureWeights(w.weight, w.bias, w.mean, w.std, f"torchvision AlexNet conv1 (cached): {cache}")
    if not download:
        raise PerchError("torchvision AlexNet weights are not cached; " + HOW_TO_PROVIDE)
    import torch.hub

    try:
        state = torch.hub.load_state_dict_from_url(TORCHVISION_ALEXNET_URL, progress=True, check_hash=True)
    except Exception as e:  # network errors come in many types
        raise PerchError(
            f"cannot download torchvision AlexNet weights ({type(e).__name__}: {e}); " + HOW_TO_PROVIDE
        ) from None
    weight, bias = _validate(state["features.0.weight"].numpy(), state["features.0.bias"].numpy(), "torchvision")
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, weight=weight, bias=bias, preprocessing="torchvision")
    os.replace(tmp, cache)
    return FeatureWeights(
        weight, bias, IMAGENET_MEAN, IMAGENET_STD, f"torchvision AlexNet conv1: {TORCHVISION_ALEXNET_URL}"
    )


def load_feature_weights(spec: str = "auto") -> FeatureWeights:
    """Resolve `spec` ("auto", "caffe", "torchvision", or an .npz path) to weights; see the module doc."""
    if spec == "caffe":
        return load_caffe()
    if spec == "torchvision":
        return load_torchvision()
    if spec == "auto":
        if caffe_weights_path() is not None:
            return load_caffe()
        return load_torchvision()
    if spec.endswith(".npz") or Path(spec).exists():
        return load_npz(spec)
    raise PerchError(f"unknown --weights {spec!r}: use auto, caffe, torchvision or a FILE.npz")
