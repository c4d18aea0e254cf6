"""ADC sampling: counts to SI units, and plausibility of each channel.

A channel is faulty when its counts are not an integer in [0, full scale] (out of range, NaN,
wrong type) or sit at a rail for ``rail_ticks`` consecutive samples (stuck at rail: a broken
wire or a saturated sensor). A faulty channel holds its last good value. The fault clears only
after ``recover_ticks`` consecutive good samples (hysteresis).

A rail the ECU's estimate explains is no fault: the motor current beyond its sensor's range
while the suspension moves so fast that the back-EMF alone drives it there
(``AdcParams.current_rail_mps``). Such a sample is clipped (``measured`` is False: it says only
that the quantity is beyond the range) and starts the count of rail samples again, so a sensor
stuck at its rail is a fault ``rail_ticks`` samples after the motion no longer explains it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from firmware.params import AdcParams

CHANNELS = ("body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")

# fault bits of the channels (the low byte of the ECU's fault word)
FAULT_BIT = {name: 1 << i for i, name in enumerate(CHANNELS)}
SPEED = CHANNELS.index("speed")


@dataclass
class ChannelState:
    value: float = 0.0          # last good value (SI)
    counts: int | None = None   # its counts (None: no good sample yet; the value is 0)
    rail_count: int = 0         # consecutive samples at a rail that nothing explains
    clipped: bool = False       # this sample is at a rail
    good_count: int = 0
    faulty: bool = False


@dataclass
class AdcState:
    channels: dict = field(default_factory=lambda: {name: ChannelState() for name in CHANNELS})


def sample(params: AdcParams, state: AdcState, counts: tuple, explained: int = 0
           ) -> tuple[tuple, int]:
    """Convert one sample of every channel: the counts in ``CHANNELS`` order (one per channel,
    else ValueError) -> (the SI values in that order, fault bits). ``explained``: the fault
    bits of the channels whose rail this sample is explained (clipped, not faulty)."""
    values = []
    faults = 0
    rail_ticks, recover_ticks = params.rail_ticks, params.recover_ticks
    chans = (params.body_accel, params.wheel_accel, params.susp_defl, params.motor_current,
             params.speed)
    for i, (ch, st, c) in enumerate(zip(chans, state.channels.values(), counts, strict=True)):
        if isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= ch.full_scale:
            # at a rail; speed legitimately sits at 0 counts when the car stands still
            at_rail = c == ch.full_scale or (c == 0 and i != SPEED)
            st.clipped = at_rail
            st.rail_count = st.rail_count + 1 if at_rail and not explained >> i & 1 else 0
            bad = st.rail_count >= rail_ticks
        else:
            st.clipped = False
            bad = True
        if bad:
            st.good_count = 0
            st.faulty = True
            faults |= 1 << i
        else:
            st.good_count += 1
            if st.faulty and st.good_count >= recover_ticks:
                st.faulty = False
            if st.faulty:
                faults |= 1 << i
            else:
                st.value = ch.range_min + c * ch.lsb
                st.counts = c
        values.append(st.value)
    return tuple(values), faults


def measured(state: AdcState, names) -> bool:
    """Every channel in ``names`` gave a measurement this tick: a good sample that is not at
    a rail (a clipped sample says only that the quantity is beyond the range)."""
    for name in names:
        c = state.channels[name]
        if c.faulty or c.clipped:
            return False
    return True
