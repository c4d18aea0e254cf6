"""The road profile's compiled kernel (``hil.sim.road`` is the model)."""

from __future__ import annotations

import numpy as np

from firmware.kernels import njit


@njit
def ar1(drive, phi):
    """h[0] = drive[0], h[n] = drive[n] + phi h[n-1]: the first-order recursion (the
    discretised Ornstein-Uhlenbeck road) with the bits of ``scipy.signal.lfilter([1],
    [1, -phi], drive)``, whose import cost half a second of every run's start."""
    h = np.empty_like(drive)
    prev = 0.0
    for n in range(drive.shape[0]):
        prev = drive[n] + phi * prev
        h[n] = prev
    return h
