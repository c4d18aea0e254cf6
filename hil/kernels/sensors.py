"""The sensors' compiled kernels (``hil.sim.sensors`` is the model): noise and ADC quantisation of one
sample of every channel, rounding half away from zero, saturating at the rails."""

from __future__ import annotations

import math

import numpy as np

from firmware.kernels import njit


@njit
def quantise5(v0, v1, v2, v3, v4, z, std, gain, range_min, lsb, full):
    """``_quantise`` of the five channels given as scalars (no array to build per call)."""
    c = quantise(np.array((v0, v1, v2, v3, v4)), z, std, gain, range_min, lsb, full)
    return c[0], c[1], c[2], c[3], c[4]


@njit
def quantise(values, z, std, gain, range_min, lsb, full):
    """to_counts(channel, value + noise) for every channel (noise = z * std * gain)."""
    out = np.empty(values.shape[0], dtype=np.int64)
    quantise_into(values, z, std, gain, range_min, lsb, full, out)
    return out


@njit
def quantise_into(values, z, std, gain, range_min, lsb, full, out) -> None:
    """``quantise`` into ``out``."""
    for i in range(values.shape[0]):
        out[i] = to_counts(values[i] + z[i] * std[i] * gain[i], range_min[i], lsb[i], full[i])


@njit
def to_counts(v, range_min, lsb, full):
    """``hil.sim.sensors.to_counts``: a value as ADC counts, NaN at the lower rail, rounded half
    away from zero, saturated at 0 and ``full``."""
    if math.isnan(v):
        return 0
    raw = (v - range_min) / lsb
    if raw <= 0.0:
        return 0
    if raw >= full:
        return full
    return int(math.floor(raw + 0.5))
