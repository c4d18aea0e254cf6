"""What the three nodes share: the DBC's message IDs and owners, a node's transmit side
(``Tx``), the receivers' specs, the lockstep log clock."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace
from typing import Callable, Iterable, Optional


from firmware import safety
from hil.sim.road import GRADES
from hil.transport.codec import Codec


Frame = tuple[int, bytes]

# message IDs (from the DBC, resolved once)
_DB = Codec()
ID = {m.name: m.frame_id for m in _DB.db.messages}
NAME_OF = {v: k for k, v in ID.items()}
OWNER = {m.name: (m.senders or [""])[0] for m in _DB.db.messages}


def period_ticks(codec: Codec, name: str, dt_s: float) -> int:
    return max(1, int(round(codec.cycle_ms(name) * 1e-3 / dt_s)))


def rx_spec(codec: Codec, check: safety.RxCheck, dt_s: float) -> safety.FrameSpec:
    """The receiver's spec of a message: the DBC's layout (DLC, COUNTER, CHECKSUM) with the
    firmware's supervision (``safety.RX_CHECKS``: timeout, minimum interval, recovery)."""
    spec = codec.specs[ID[check.message]]
    _, timeout, min_interval = check.ticks(dt_s)
    if not check.counter_checksum:
        spec = replace(spec, counter_bit=None, checksum_byte=None)
    return replace(spec, timeout_ticks=timeout, min_interval_ticks=min_interval,
                   recover_frames=check.recover_frames)


# the grades the ECU's estimate names (firmware.grade: 0..3, A to D); a rougher road (E-H)
# reads as D, its cap: SIM_TRUTH's TRUE_GRADE carries it capped, and a drive's grade accuracy
# scores only the segments the estimate can name (hil.nodes.sil)
NAMED_GRADES = 4


def true_grade_index(grade: str) -> int:
    return min(NAMED_GRADES - 1, GRADES.index(grade))


def grade_named(grade: str) -> bool:
    """The ECU's grade estimate can name ``grade`` (A-D)."""
    return GRADES.index(grade) < NAMED_GRADES


class Tx:
    """A node's transmit side: one COUNTER per message, frames sent counted per message."""

    def __init__(self, codec: Codec, allowed: Optional[Iterable[str]] = None):
        self.codec = codec
        self.counters: dict[str, int] = {}
        self.sent: Counter = Counter()
        self.allowed = None if allowed is None else frozenset(allowed)

    def _count(self, name: str) -> int:
        """The COUNTER for the next frame of ``name`` (and that frame counted as sent)."""
        if self.allowed is not None and name not in self.allowed:
            raise ValueError(f"{name} is not on this node's transmit list")
        c = self.counters.get(name, 0)
        self.counters[name] = (c + 1) & 0xF
        self.sent[name] += 1
        return c

    def frame(self, name: str, raw: dict) -> Frame:
        return ID[name], self.codec.encode_raw(name, raw, self._count(name))

    def frame_packed(self, name: str, pack: Callable[..., bytes], values: tuple) -> Frame:
        """``frame`` with the raw values by position, packed by ``pack``
        (``Codec.packer(name, signals)``): the per-tick frames."""
        return ID[name], pack(values, self._count(name))

    def frame_phys(self, name: str, values: dict) -> Frame:
        return ID[name], self.codec.encode(name, values, self._count(name))


MISSING = object()   # a tick without a sensor frame (SIM_TICK: the ECU's timer ran alone)
_FORGED = object()   # a secured frame whose MAC or freshness failed


class LockstepClock:
    """Log timestamps in lockstep pacing: simulated time. Tick k runs from the frame after
    ACTUATOR_CMD(k-1) to ACTUATOR_CMD(k); frames inside a tick are 1 us apart."""

    def __init__(self, dt_s: float):
        self.dt_us = int(round(dt_s * 1e6))
        self.tick = 0
        self.j = 0

    def stamp(self, fid: int) -> float:
        us = self.tick * self.dt_us + self.j
        self.j += 1
        if fid == ID["ACTUATOR_CMD"]:
            self.tick += 1
            self.j = 0
        return us / 1e6


def message_name(fid: int) -> str:
    """The DBC name of a frame ID (``0x123`` for an ID the DBC does not define)."""
    return NAME_OF.get(fid) or f"0x{fid:X}"
