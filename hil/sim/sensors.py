"""Sensor models: white Gaussian noise (seeded) and ADC quantisation with saturation.

An ADC channel maps [range_min, range_max] onto counts 0 .. 2^bits - 1 (offset binary),
rounding half away from zero and saturating at the rails, never wrapping.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np

from calib.vehicle import SENSOR_NAMES, SensorChannel, SensorParams
from firmware.fixedpoint import round_half_away
from hil.kernels import sensors as kern
from hil.kernels.frames import table

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
        self.fault: Optional[np.ndarray] = None       # a sensor fault (kern.FAULT, one record)
        self._noise = np.empty((0, len(SENSOR_NAMES)))
        self._next = 0

    def set_fault(self, channel: str, kind: str, onset: int, size: float = 0.0) -> None:
        """A persistent fault of one channel (``SENSOR_NAMES``) from tick ``onset``:
        ``kern.FAULT_KINDS``' bias, drift (``size`` per tick), gain (excess), stuck, noise
        (factor) or dropout."""
        if channel not in SENSOR_NAMES or kind not in kern.FAULT_KINDS[1:]:
            raise ValueError(f"sensor fault: no channel {channel!r} or kind {kind!r}")
        if not math.isfinite(size) or onset < 0:
            raise ValueError(f"sensor fault: size {size!r}, onset {onset!r}")
        f = table(kern.FAULT, 1)
        f["channel"], f["kind"], f["onset"] = (SENSOR_NAMES.index(channel),
                                               kern.FAULT_KINDS.index(kind), onset)
        f["size"], f["held"] = size, -1
        f["zero"] = to_counts(getattr(self.params, channel), 0.0)
        self.fault = f

    def sample(self, body_accel: float, wheel_accel: float, susp_defl: float,
               motor_current: float, speed: float, k: int = 0) -> SensorReading:
        """The counts of tick ``k`` (which only a ``fault`` reads)."""
        if self._next >= len(self._noise):
            self._noise = self.rng.standard_normal((NOISE_BLOCK, len(self._channels)))
            self._next = 0
        z = self._noise[self._next]
        self._next += 1
        if self.fault is not None:
            out = np.empty(len(self._channels), dtype=np.int64)
            kern.quantise_faulted(np.array((body_accel, wheel_accel, susp_defl, motor_current,
                                            speed), dtype=float), z, self._std,
                                  self.noise_gain, self._min, self._lsb, self._full, out,
                                  self.fault, k)
            return SensorReading(*(int(v) for v in out))
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
