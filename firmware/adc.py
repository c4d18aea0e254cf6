"""ADC sampling: counts to SI units, and plausibility of each channel.

A channel is faulty when its counts are not an integer in [0, full scale] (out of range, NaN,
wrong type) or sit at a rail for ``rail_ticks`` consecutive samples (stuck at rail: a broken
wire or a saturated sensor). A faulty channel holds its last good value. The fault clears only
after ``recover_ticks`` consecutive good samples (hysteresis).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from firmware.params import AdcChannel, AdcParams

CHANNELS = ("body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")

# fault bits of the channels (the low byte of the ECU's fault word)
FAULT_BIT = {name: 1 << i for i, name in enumerate(CHANNELS)}


@dataclass
class ChannelState:
    value: float = 0.0          # last good value (SI)
    counts: int | None = None   # its counts (None: no good sample yet; the value is 0)
    rail_count: int = 0
    good_count: int = 0
    faulty: bool = False


@dataclass
class AdcState:
    channels: dict = field(default_factory=lambda: {name: ChannelState() for name in CHANNELS})


def counts_to_si(channel: AdcChannel, counts: int) -> float:
    return channel.range_min + counts * channel.lsb


def _valid_counts(channel: AdcChannel, counts) -> bool:
    return isinstance(counts, int) and not isinstance(counts, bool) and 0 <= counts <= channel.full_scale


def sample(params: AdcParams, state: AdcState, raw: dict) -> tuple[dict, int]:
    """Convert one sample of every channel. Returns ({name: SI value}, fault bits)."""
    values = {}
    faults = 0
    for name in CHANNELS:
        ch: AdcChannel = getattr(params, name)
        st: ChannelState = state.channels[name]
        counts = raw.get(name)
        if _valid_counts(ch, counts):
            at_rail = counts == 0 or counts == ch.full_scale
            # speed legitimately sits at 0 counts when the car stands still
            if name == "speed" and counts == 0:
                at_rail = False
            st.rail_count = st.rail_count + 1 if at_rail else 0
            bad = st.rail_count >= params.rail_ticks
        else:
            bad = True
        if bad:
            st.good_count = 0
            st.faulty = True
        else:
            st.good_count += 1
            if st.faulty and st.good_count >= params.recover_ticks:
                st.faulty = False
            if not st.faulty:
                st.value = counts_to_si(ch, counts)
                st.counts = counts
        if st.faulty:
            faults |= FAULT_BIT[name]
        values[name] = st.value
    return values, faults
