"""The grade estimate's compiled kernel: np.interp for one point, the same bits."""

from __future__ import annotations

import math

from firmware.kernels import njit


@njit
def interp(x, xp, fp):
    """np.interp for one point, with numpy's formula (the same bits): linear between grid
    points, the end values outside, NaN for NaN."""
    n = xp.shape[0]
    if math.isnan(x):
        return math.nan
    if x <= xp[0]:
        return fp[0]
    if x >= xp[n - 1]:
        return fp[n - 1]
    j = 0
    while xp[j + 1] <= x:
        j += 1
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    r = slope * (x - xp[j]) + fp[j]
    if math.isnan(r):
        r = slope * (x - xp[j + 1]) + fp[j + 1]
        if math.isnan(r) and fp[j] == fp[j + 1]:
            r = fp[j]
    return r
