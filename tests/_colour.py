"""The tests' own sRGB reference (IEC 61966-2-1), written out in NumPy, independent of the kernels'."""

import numpy as np


def srgb_exposed(c, gain):
    """sRGB colours c in [0, 1] as a camera exposed `gain` times brighter records them: linear light,
    clipped at white (gain < 1 darkens, as the shade term's light does)."""
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    x = np.minimum(gain * lin, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
