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


# -- a persistent single-sensor fault (``hil.validate.sensorfaults``: the sensor campaign) --
# one record: the channel (index into the five; -1: none), the kind, the tick of its onset,
# its size (bias: the value added; drift: the value added per tick since the onset; gain: the
# excess g - 1 of the true value's gain; noise: the noise's factor), the stuck count (held
# from the onset's sample; -1 until then) and the count a dropout reads (the ADC's count of 0)
FAULT = np.dtype([("channel", "i8"), ("kind", "i8"), ("onset", "i8"), ("size", "f8"),
                  ("held", "i8"), ("zero", "i8")])
FAULT_KINDS = ("none", "bias", "drift", "gain", "stuck", "noise", "dropout")
K_BIAS, K_DRIFT, K_GAIN, K_STUCK, K_NOISE, K_DROPOUT = 1, 2, 3, 4, 5, 6
DROPOUT_ON, DROPOUT_PERIOD = 5, 100      # a dropout reads 0 for 5 ticks of every 100


@njit
def quantise_faulted(values, z, std, gain, range_min, lsb, full, out, F, k) -> None:
    """``quantise_into`` with the fault ``F[0]`` from its onset: a bias, drift or gain on the
    sensor's true value, a noise ``size`` times its own (the same draws), before the ADC; a
    stuck or dropped-out count after it."""
    f = F[0]
    c = f.channel
    on = c >= 0 and k >= f.onset
    if on:
        if f.kind == K_BIAS:
            values[c] += f.size
        elif f.kind == K_DRIFT:
            values[c] += f.size * (k - f.onset)
        elif f.kind == K_GAIN:
            values[c] *= 1.0 + f.size
        elif f.kind == K_NOISE:
            values[c] += (f.size - 1.0) * z[c] * std[c] * gain[c]
    quantise_into(values, z, std, gain, range_min, lsb, full, out)
    if on:
        if f.kind == K_STUCK:
            if f.held < 0:
                F[0].held = out[c]
            out[c] = F[0].held
        elif f.kind == K_DROPOUT and (k - f.onset) % DROPOUT_PERIOD < DROPOUT_ON:
            out[c] = f.zero
