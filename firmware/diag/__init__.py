"""Diagnostics as in a production ECU: model-based fault detection (``fdi``), the DTC memory
with ISO 14229 status bytes and snapshots (``dtc``), and the UDS service dispatch (``uds``:
request bytes in, response bytes out). Pure code: time is the tick count."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from firmware.diag import dtc, fdi
from firmware.fixedpoint import round_half_away

SESSION_DEFAULT, SESSION_EXTENDED = 0x01, 0x03


@dataclass
class DiagState:
    fdi: fdi.FdiState = field(default_factory=fdi.FdiState)
    dtc: dtc.DtcMemory = field(default_factory=dtc.DtcMemory)
    session: int = SESSION_DEFAULT
    session_tick: int = 0          # the tick of the last request in a non-default session
    reset_requested: int = 0       # 0x11's reset type, for the node to carry out
    # the last tick's values the DIDs and snapshots read: mode, grade, fault word,
    # speed (cm/s, 0xFFFF unknown), BA RMS (mm/s^2), DTD RMS (um), tick, supply (mV, 0xFFFF
    # not measured yet)
    view: tuple = (0, 255, 0, 0xFFFF, 0, 0, -1, 0xFFFF)

    def __post_init__(self):
        self.snap = lambda tick: snapshot_of(self, tick)   # (the DTC memory's callback)


def snapshot_of(ds: DiagState, tick: int) -> dtc.Snapshot:
    """The freeze frame of a failure at ``tick``: the values of the tick before (the state
    the fault appeared in, before any fail-safe reaction), but the supply voltage as last
    measured (a supply fault's own sample)."""
    mode, grade, _, speed, ba, dtd, _, _ = ds.view
    return dtc.Snapshot(tick, speed, grade, mode, ba, dtd, supply_mv(ds.fdi.supply_v))


def supply_mv(volts: float) -> int:
    """The supply voltage as the DIDs and snapshots carry it: mV, 0xFFFF not measured yet."""
    return 0xFFFF if math.isnan(volts) else min(0xFFFE, max(0, round_half_away(volts * 1000.0)))
