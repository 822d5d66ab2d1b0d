"""The Warp device the kernel tests run on: Warp's CPU device (CI), or $PERCH_WARP_TEST_DEVICE (e.g. cuda:0)."""

import os

DEVICE = os.environ.get("PERCH_WARP_TEST_DEVICE", "cpu")
