"""Sensor models: white Gaussian noise (seeded) and ADC quantisation with saturation.

An ADC channel maps [range_min, range_max] onto counts 0 .. 2^bits - 1 (offset binary),
rounding half away from zero and saturating at the rails, never wrapping.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from calib.vehicle import SENSOR_NAMES, SensorChannel, SensorParams
from firmware.fixedpoint import round_half_away
from hil.kernels import sensors as kern

NOISE_BLOCK = 256   # ticks of noise drawn at once (the same stream as one draw per tick)


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


class SensorReading(NamedTuple):
    """One sample of every channel in ADC counts."""

    body_accel: int
    wheel_accel: int
    susp_defl: int
    motor_current: int
    speed: int


class SensorSuite:
    """All sensors of the corner, with one seeded generator for their noise. The noise is
    drawn ``NOISE_BLOCK`` samples ahead; numpy's generator fills a block in the order of
    single draws, so the values are those of one draw per sample."""

    def __init__(self, params: SensorParams, rng: np.random.Generator):
        self.params = params
        self.rng = rng
        self._channels = [getattr(params, name) for name in SENSOR_NAMES]
        self._std = np.array([c.noise_std for c in self._channels])
        self._min = np.array([c.range_min for c in self._channels])
        self._lsb = np.array([c.lsb for c in self._channels])
        self._full = np.array([2**c.bits - 1 for c in self._channels], dtype=np.int64)
        self.noise_gain = np.ones(len(SENSOR_NAMES))  # scenario knob: multiply the noise
        self._noise = np.empty((0, len(SENSOR_NAMES)))
        self._next = 0

    def sample(self, body_accel: float, wheel_accel: float, susp_defl: float,
               motor_current: float, speed: float) -> SensorReading:
        if self._next >= len(self._noise):
            self._noise = self.rng.standard_normal((NOISE_BLOCK, len(self._channels)))
            self._next = 0
        z = self._noise[self._next]
        self._next += 1
        return SensorReading(*kern.quantise5(float(body_accel), float(wheel_accel),
                                         float(susp_defl), float(motor_current), float(speed),
                                         z, self._std, self.noise_gain, self._min, self._lsb,
                                         self._full))


class SupplySensor:
    """The supply-voltage channel, sampled every 10 ms: Gaussian noise from its own seeded
    stream (the other channels draw what they drew before it existed), then the ADC."""

    def __init__(self, channel: SensorChannel, rng: np.random.Generator):
        self.channel, self.rng = channel, rng

    def sample(self, volts: float) -> int:
        return to_counts(self.channel, volts + self.channel.noise_std * self.rng.standard_normal())
