"""Shared fixtures. Everything runs on Warp's CPU device; data from ../shared is optional."""

from __future__ import annotations

import numpy as np
import pytest

from perch_warp.features import FeatureWeights, caffe_weights_path, load_caffe
from perch_warp.paths import shared_dir


@pytest.fixture(scope="session")
def shared():
    root = shared_dir()
    if root is None:
        pytest.skip("shared/ data folder not found (set PERCH_WARP_SHARED or put it beside the repository)")
    return root


@pytest.fixture(scope="session")
def caffe_weights() -> FeatureWeights:
    if caffe_weights_path() is None:
        pytest.skip("Caffe AlexNet conv1 weights (shared/weights/bvlc_alexnet_conv1.npz) not found")
    return load_caffe()


@pytest.fixture(scope="session")
def random_weights() -> FeatureWeights:
    """96 random 11x11 filters: the same kernel shapes as Caffe's, available everywhere."""
    rng = np.random.default_rng(7)
    w = rng.normal(0, 0.05, (96, 3, 11, 11)).astype(np.float32)
    b = rng.normal(0, 0.1, 96).astype(np.float32)
    return FeatureWeights(w, b, (0.4, 0.45, 0.5), (0.25, 0.2, 0.3), "random test filters")
