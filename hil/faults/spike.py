"""A sensor that spikes for one sample, then recovers (an electrical glitch: a connector's
bounce, an ESD event). The ECU is meant to ride through it: one sample inside the sensor's
range is not a fault, so no fault bit, no fail-safe tick and control goes on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware import safety
from hil.faults.base import Evidence, Fault, Result, Window, raw_signal, reencode
from hil.faults.sensors import SIGNAL


@dataclass(frozen=True, kw_only=True)
class SensorSpike(Fault):
    """One PLANT_SENSORS sample of ``channel`` off by ``counts`` (clamped to its range)."""
    channel: str = "ba"
    counts: int = 0
    safety: bool = False

    def after_emit(self, inj, plant, frames, w: Window):
        sig = SIGNAL[self.channel]
        raw, full = raw_signal(plant.codec, frames[-1], sig)
        frames[-1] = reencode(plant.codec, frames[-1],
                              **{sig: min(full, max(0, raw + self.counts))})
        inj.mark(self.name, plant.k)
        return frames

    def judge(self, ev: Evidence) -> Result:
        seg = ev.seg
        bits = safety.fault_names(int(np.bitwise_or.reduce(ev.faults[seg])))
        stopped = int(np.count_nonzero(~ev.enable[seg]))
        ridden = not bits and stopped == 0
        return Result(self.name, None, None, ridden, ev.crashed, False, fault_bits=bits,
                      failsafe_ticks=stopped,
                      note="ridden through: no fault bit, no fail-safe tick" if ridden
                      else "the glitch stopped control")

    def holds(self, r: Result) -> bool:
        return not r.crashed and r.recovered is True

    def limit_text(self, r: Result) -> str:
        return "ridden through: no fault bit, no fail-safe tick"

    def value_text(self, r: Result) -> str:
        return "crashed" if r.crashed else (
            "ridden through" if r.recovered else
            f"fault bits {', '.join(r.fault_bits) or 'none'}, {r.failsafe_ticks} fail-safe ticks")

    def table_note(self, r: Result) -> str:
        return r.note
