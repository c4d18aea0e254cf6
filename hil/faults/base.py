"""The fault family's base class, the schedule's window, and the campaign's row (``Result``)
with the evidence a family judges from."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from firmware import params as fp
from firmware import safety
from hil.nodes import Frame

MAX_REACTION_TICKS = 3          # safety-relevant faults: fail-safe within this many ticks
MAX_PLAUSIBLE_TICKS = 200       # plausible sensor faults: detected and fail-safe within 200 ms
MAX_ACTUATOR_TICKS = 20         # actuator and supply faults: within 20 ms
PLAUSIBLE_TICKS = 300           # their windows
CAMPAIGN_MODE = "comfort"       # the ECU drives actively (BP-PID) between faults
CAMPAIGN_GRADE = "B"
CAMPAIGN_SPEED_MPS = 20.0
SNAPSHOT_SPEED_TOL_MPS = 0.2    # a DTC's snapshot: the drive's speed within this
REPLAY_AGE_TICKS = 100          # a replayed command was recorded this many ticks earlier


@dataclass(frozen=True)
class Window:
    name: str
    node: str
    start: int
    ticks: int


@dataclass
class Result:
    fault: str
    detected: Optional[bool]          # None: not to be detected (a glitch to ride through)
    reaction_ticks: Optional[int]
    recovered: Optional[bool]
    crashed: bool
    safety_relevant: bool
    recovery_ticks: Optional[int] = None
    driver_told: Optional[bool] = None
    fault_bits: list = None
    failsafe_ticks: int = 0
    mode_kept: Optional[bool] = None
    note: str = ""
    dtc: list = None                  # plausible faults: the DTCs read over UDS after it
    detect_ms: Optional[float] = None  # first faulty tick to detection
    isolated: Optional[bool] = None   # the faulty part named (None: not claimed for this fault)
    isolation: Optional[str] = None   # what the confirmed DTCs name: "right" (the faulty part
    #                                   only), "not isolated" (no part: the bank could not
    #                                   tell), "wrong" (a healthy part), None (no DTC)
    snapshot_ok: Optional[bool] = None  # its snapshot: in the window, the drive's speed
    degraded: Optional[str] = None    # plausible faults: what degraded operation did in the
    #                                   segment (hil.faults.sensors.degraded_seen)


@dataclass
class Evidence:
    """What a window is judged from: the ECU's and the plant's per-tick records from the
    fault's first faulty tick to the next window (``seg``), what the injector did (``applied``:
    first tick, last tick, frames touched), what the driver app was told, the hub's log and
    the DTCs the tester read after it."""
    window: Window
    applied: list
    end: int
    faults: np.ndarray
    enable: np.ndarray
    modes: np.ndarray
    fallback: np.ndarray
    plant: dict
    faults_seen: list
    crashed: bool
    mode: int
    hub_log: str = ""
    dtc_read: Optional[dict] = None
    degraded: Optional[np.ndarray] = None   # the ECU's degraded state per tick

    @property
    def first(self) -> int:
        return self.applied[0]

    @property
    def last(self) -> int:
        return self.applied[1]

    @property
    def seg(self) -> slice:
        return slice(self.first, self.end)


@dataclass(frozen=True, kw_only=True)
class Fault:
    """A fault of one family. ``node`` is the path it breaks: ``plant`` (what the plant
    sends), ``plant_rx`` (what it receives), ``plant_hw`` (its bridge, winding, supply),
    ``app`` (the driver app's requests), ``bus`` (an outside client), ``config`` (a file the
    ECU reads). ``ticks``: the window; ``safety``: fail-safe within ``limit`` ticks; ``expect``:
    the ECU fault bits naming it; ``dtc``: the DTC that isolates it (plausible faults)."""
    name: str
    what: str
    node: str = "plant"
    ticks: int = 1
    safety: bool = True
    expect: int = 0
    limit: int = MAX_REACTION_TICKS
    dtc: str = ""
    plausible: bool = False           # a model-based detection (firmware.diag.fdi)
    note: str = ""
    needs_hub: bool = False           # only where a hub runs (not on vcan0)

    # -- the hooks (a family implements the one of its node) ----------------------------------

    def before_emit(self, inj, plant, w: Window) -> None:
        """The plant is about to sample and send tick ``plant.k``."""

    def after_emit(self, inj, plant, frames: list, w: Window) -> list:
        """The frames the plant sends this tick (PLANT_SENSORS last): changed, dropped, added."""
        return frames

    def hardware(self, inj, plant, cmd: tuple, w: Window) -> tuple:
        """(duty Q15, regen, enable) as the corner's bridge actually gets it this tick."""
        return cmd

    def drop_rx(self, inj, plant, fid: int, w: Window) -> bool:
        """The plant's receiver loses this frame."""
        return False

    def rx_extra(self, inj, plant, w: Window) -> list:
        """Frames the plant receives before the real ACTUATOR_CMD."""
        return []

    def before_answer(self, inj, app, w: Window) -> None:
        """The app is about to answer a MODE_RECOMMEND."""

    # -- judging --------------------------------------------------------------------------------

    def reaction(self, ev: Evidence) -> tuple:
        """(ticks of the segment that count as the reaction, ticks in a faulty state, the fault
        bits named): by default the ECU's fault word and its bridge."""
        seg = ev.seg
        hit = np.flatnonzero(~ev.enable[seg] if self.safety else (ev.faults[seg] & self.expect))
        if self.safety:   # detected means named too, not only disabled
            hit = hit if np.any(ev.faults[seg] & self.expect) else hit[:0]
        bad = (ev.faults[seg] != 0) | ~ev.enable[seg]
        return hit, bad, safety.fault_names(int(np.bitwise_or.reduce(ev.faults[seg])))

    def judge(self, ev: Evidence) -> Result:
        hit, bad, bits = self.reaction(ev)
        first, last, end, seg = ev.first, ev.last, ev.end, ev.seg
        detected = hit.size > 0
        bad_idx = np.flatnonzero(bad)
        last_bad = first + int(bad_idx[-1]) if bad_idx.size else last
        recovered = bool(detected and last_bad < end - 1)
        told = None
        if self.expect:
            told = any(first <= t < end and f & self.expect for t, f, _ in ev.faults_seen)
        kept = None
        if self.node == "app":
            kept = bool(np.all((ev.modes[seg] == ev.mode) | (ev.modes[seg] == fp.MODE_PASSIVE)))
        return Result(
            self.name, detected, int(hit[0]) if detected else None, recovered, ev.crashed,
            self.safety, recovery_ticks=max(0, last_bad - last) if recovered else None,
            driver_told=told, fault_bits=bits,
            failsafe_ticks=int(np.count_nonzero(~ev.enable[seg])), mode_kept=kept,
            note=self.note)

    def holds(self, r: Result) -> bool:
        return (r.detected and not r.crashed
                and (not r.safety_relevant or (r.reaction_ticks or 0) <= self.limit)
                and r.recovered is not False)

    def limit_text(self, r: Result) -> str:
        """What the verdict's check of this fault demands."""
        out = "detected" + (f", fail-safe within {self.limit} ticks" if r.safety_relevant
                            else "")
        return out + (", recovered" if r.recovered is not None else "")

    def value_text(self, r: Result) -> str:
        """What the fault's row showed, in the verdict's words."""
        if r.crashed:
            return "crashed"
        if not r.detected:
            return "missed"
        if r.recovered is False:
            return f"reaction {r.reaction_ticks} ticks, not recovered"
        return f"reaction {r.reaction_ticks} ticks"

    def table_note(self, r: Result) -> str:
        """The table's "fault bits" cell."""
        return ", ".join(r.fault_bits or [])

    def row(self) -> dict[str, Any]:
        return {"name": self.name, "node": self.node, "what": self.what}


def memo(inj, fault: Fault) -> dict:
    """A family's own state in one injector (the registry's instances are shared)."""
    return inj.memo.setdefault(fault.name, {})


def name_of(codec, fid: int) -> str:
    return codec.db.get_message_by_frame_id(fid).name


def reencode(codec, frame: Frame, **raw_over) -> Frame:
    """The same frame with some raw signal values replaced, COUNTER kept, CHECKSUM resealed
    (a sensor or sender fault, not a transmission error)."""
    fid, data = frame
    name = name_of(codec, fid)
    raw = dict(codec.decode(fid, data, scaling=False).signals)
    raw.update(raw_over)
    return fid, codec.encode_raw(name, raw, raw.get("COUNTER", 0))


def raw_signal(codec, frame: Frame, signal: str) -> tuple[int, int]:
    """A signal's raw value in a frame, and its maximum raw value (the DBC's)."""
    raw = codec.decode(frame[0], frame[1], scaling=False).signals[signal]
    full = int(codec.message(name_of(codec, frame[0])).get_signal_by_name(signal).maximum)
    return raw, full
