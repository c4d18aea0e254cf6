"""Sensor models: white Gaussian noise (seeded) and ADC quantisation with saturation.

An ADC channel maps [range_min, range_max] onto counts 0 .. 2^bits - 1 (offset binary),
rounding half away from zero and saturating at the rails, never wrapping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hil.config import SENSOR_NAMES, SensorChannel, SensorParams


def round_half_away(x: float) -> int:
    """Round half away from zero (the project's one rounding rule, Python and C alike)."""
    return int(math.floor(x + 0.5)) if x >= 0 else -int(math.floor(-x + 0.5))


def to_counts(channel: SensorChannel, value: float) -> int:
    """Quantise a physical value to ADC counts, saturating at 0 and full scale.
    NaN reads as the lower rail (what a floating input typically gives)."""
    full = 2**channel.bits - 1
    if math.isnan(value):
        return 0
    raw = (value - channel.range_min) / channel.lsb
    if raw <= 0.0:
        return 0
    if raw >= full:
        return full
    return round_half_away(raw)


def from_counts(channel: SensorChannel, counts: int) -> float:
    return channel.range_min + counts * channel.lsb


@dataclass(frozen=True)
class SensorReading:
    """One sample of every channel in ADC counts."""

    body_accel: int
    wheel_accel: int
    susp_defl: int
    motor_current: int
    speed: int


class SensorSuite:
    """All sensors of the corner, with one seeded generator for their noise."""

    def __init__(self, params: SensorParams, rng: np.random.Generator):
        self.params = params
        self.rng = rng
        self._channels = [getattr(params, name) for name in SENSOR_NAMES]
        self._std = np.array([c.noise_std for c in self._channels])
        self.noise_gain = np.ones(len(SENSOR_NAMES))  # scenario knob: multiply the noise

    def sample(self, body_accel: float, wheel_accel: float, susp_defl: float,
               motor_current: float, speed: float) -> SensorReading:
        noise = self.rng.standard_normal(len(self._channels)) * self._std * self.noise_gain
        values = (body_accel, wheel_accel, susp_defl, motor_current, speed)
        counts = [to_counts(c, v + n) for c, v, n in zip(self._channels, values, noise)]
        return SensorReading(*counts)
