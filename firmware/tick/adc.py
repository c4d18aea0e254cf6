"""Stage 1, ADC sampling, compiled (``firmware.adc`` says what it does): counts to SI values,
a channel's fault when its counts are out of range or sit at a rail for ``rail_ticks``
samples that nothing explains, recovery after ``recover_ticks`` good samples."""

from __future__ import annotations

import numpy as np

from firmware.adc import CHANNELS, SPEED
from firmware.kernels import njit

N = len(CHANNELS)
BA, WA, DEFL, CUR = (CHANNELS.index(n) for n in ("body_accel", "wheel_accel", "susp_defl",
                                                   "motor_current"))
STATE = np.dtype([
    ("value", "f8", (N,)),        # last good value (SI)
    ("counts", "i8", (N,)),       # its counts (-1: no good sample yet; the value is 0)
    ("rail_count", "i8", (N,)),   # consecutive samples at a rail that nothing explains
    ("clipped", "u1", (N,)),      # this sample is at a rail
    ("good_count", "i8", (N,)),
    ("faulty", "u1", (N,)),
])


def init(S) -> None:
    S.counts[:] = -1


@njit
def sample(P, S, counts, explained) -> int:
    """One sample of every channel (``counts`` in CHANNELS order, -1: none); returns the
    fault bits. ``explained``: the bits of the channels whose rail this sample is
    explained (clipped, not faulty)."""
    faults = 0
    for i in range(N):
        c = counts[i]
        if 0 <= c <= P.full_scale[i]:
            # at a rail; speed legitimately sits at 0 counts when the car stands still
            at_rail = c == P.full_scale[i] or (c == 0 and i != SPEED)
            S.clipped[i] = at_rail
            if at_rail and not (explained >> i) & 1:
                S.rail_count[i] += 1
            else:
                S.rail_count[i] = 0
            bad = S.rail_count[i] >= P.rail_ticks
        else:
            S.clipped[i] = False
            bad = True
        if bad:
            S.good_count[i] = 0
            S.faulty[i] = True
            faults |= 1 << i
        else:
            S.good_count[i] += 1
            if S.faulty[i] and S.good_count[i] >= P.recover_ticks:
                S.faulty[i] = False
            if S.faulty[i]:
                faults |= 1 << i
            else:
                S.value[i] = P.range_min[i] + c * P.lsb[i]
                S.counts[i] = c
    return faults


@njit
def measured(S, i) -> bool:
    """Channel ``i`` gave a measurement this tick: a good sample not at a rail."""
    return not (S.faulty[i] or S.clipped[i])


@njit
def good_count(S, i) -> int:
    """This tick's counts of channel ``i`` where the ADC found them good, else -1."""
    return -1 if S.faulty[i] or S.good_count[i] == 0 else S.counts[i]
