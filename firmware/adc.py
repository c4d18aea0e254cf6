"""ADC sampling: counts to SI units, and plausibility of each channel.

A channel is faulty when its counts are not an integer in [0, full scale] (out of range, NaN,
wrong type) or sit at a rail for ``rail_ticks`` consecutive samples (stuck at rail: a broken
wire or a saturated sensor). A faulty channel holds its last good value. The fault clears only
after ``recover_ticks`` consecutive good samples (hysteresis).

No sample at all (``NO_SAMPLE``: the frame was lost, late or invalid) is not a fault of the
channel: the frame checks name it (a timeout, a CHECKSUM, ...). The channel holds its value,
is not measured this tick (``held``), and its fault state and counters stay as they were. The
ECU stays fail-safe until ``recover_ticks`` samples have come since (``unsettled``): the same
hysteresis as a channel fault's, without naming the channel.

A rail the ECU's estimate explains is no fault: the motor current beyond its sensor's range
while the suspension moves so fast that the back-EMF alone drives it there
(``AdcParams.current_rail_mps``). Such a sample is clipped (``measured`` is False: it says only
that the quantity is beyond the range) and starts the count of rail samples again, so a sensor
stuck at its rail is a fault ``rail_ticks`` samples after the motion no longer explains it.

Compiled (numba) over the state record's ``adc`` fields (``firmware.layout``).
"""

from __future__ import annotations

import numpy as np

from firmware.kernels import njit

CHANNELS = ("body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")
# fault-word bit of each channel (bits 0-4; firmware.safety defines the others)
FAULT_BIT = {name: 1 << i for i, name in enumerate(CHANNELS)}
SPEED = CHANNELS.index("speed")

N = len(CHANNELS)
NO_SAMPLE = -1                    # counts: no sample this tick (the frame layer names why)
INVALID = -2                      # counts: a sample that is no number of counts at all
BA, WA, DEFL, CUR = (CHANNELS.index(n) for n in ("body_accel", "wheel_accel", "susp_defl",
                                                   "motor_current"))
STATE = np.dtype([
    ("value", "f8", (N,)),        # last good value (SI)
    ("counts", "i8", (N,)),       # its counts (-1: no good sample yet; the value is 0)
    ("rail_count", "i8", (N,)),   # consecutive samples at a rail that nothing explains
    ("clipped", "u1", (N,)),      # this sample is at a rail
    ("good_count", "i8", (N,)),
    ("faulty", "u1", (N,)),
    ("missing", "u1", (N,)),      # no sample this tick
    ("since_missing", "i8", (N,)),  # samples since the last tick without one
])
SETTLED = 1 << 40                 # (since_missing: none missing yet)


def init(S) -> None:
    S.counts[:] = -1
    S.since_missing[:] = SETTLED


@njit
def sample(P, S, counts, explained) -> int:
    """One sample of every channel (``counts`` in CHANNELS order, NO_SAMPLE: none); returns
    the fault bits. ``explained``: the bits of the channels whose rail this sample is
    explained (clipped, not faulty)."""
    faults = 0
    for i in range(N):
        c = counts[i]
        S.missing[i] = c == NO_SAMPLE
        if S.missing[i]:                 # (the frame's fault, not the channel's)
            S.clipped[i] = False
            S.since_missing[i] = 0
            if S.faulty[i]:
                faults |= 1 << i
            continue
        S.since_missing[i] = min(SETTLED, S.since_missing[i] + 1)
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
    return not (S.faulty[i] or S.clipped[i] or S.missing[i])


@njit
def held(S, i) -> bool:
    """Channel ``i``'s value is an old one this tick: faulty or no sample."""
    return S.faulty[i] or S.missing[i]


@njit
def unsettled(P, S) -> bool:
    """A channel got no sample this tick or fewer than ``recover_ticks`` samples since."""
    for i in range(N):
        if S.since_missing[i] < P.recover_ticks:
            return True
    return False


@njit
def good_count(S, i) -> int:
    """This tick's counts of channel ``i`` where the ADC found them good, else -1."""
    return -1 if S.faulty[i] or S.missing[i] or S.good_count[i] == 0 else S.counts[i]
