"""Fault injection and the reliability campaign: ``python -m hil faults [--json]``.

The injector sits in the transmit and receive path of the plant and the driver-app nodes (a
faulty transceiver, a broken sensor, a babbling sender, a careless app) and changes what they
put on the bus, on a fixed schedule of tick windows. One lockstep run over the bus (hub or
vcan0) drives the ECU through every bus fault in turn, separated by fault-free gaps; the
configuration faults are separate ECU starts with a broken file. Each fault is then judged from
the ECU's per-tick record (fault word, bridge enable), the plant's (passive fallback) and what
the driver app received (ECU_STATUS FAULTS/REASON):

* ``detected``: the fault's bit is set in the ECU's fault word (actuator-command loss: the plant
  fell back to passive; a broken configuration file: a one-line error, exit code 2);
* ``reaction_ticks``: ticks from the first faulty tick to the fail-safe state (bridge disabled,
  no active force) for a safety-relevant fault, to the fault bit otherwise;
* ``recovered``: after the fault, the ECU is back to a clean fault word with the bridge enabled
  before the next fault; ``recovery_ticks`` counts from the last faulty tick (the hysteresis:
  at least the ADC's run of good samples for a sensor fault);
* ``crashed``: a node died or printed a traceback;
* ``driver_told``: the app received an ECU_STATUS naming the fault.

Everything is deterministic: the same seed gives the same campaign over the hub and in one
process (``--in-process``), tick for tick.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import re
import subprocess
import threading
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from firmware import adc, safety
from firmware import params as fp
from hil.nodes import ID, Frame

MAX_REACTION_TICKS = 3          # safety-relevant faults: fail-safe within this many ticks
CAMPAIGN_MODE = "comfort"       # the ECU drives actively (BP-PID) between faults
CAMPAIGN_GRADE = "B"
CAMPAIGN_SPEED_MPS = 20.0
UNKNOWN_FRAME_ID = 0x123        # not in the DBC
OUT_OF_RANGE_SPEED_RAW = 7500   # 75 m/s: inside 13 bits, outside the declared [0, 70] m/s
INVALID_MODE = 6                # REQ_MODE 6: no such mode
GAP_TICKS = 700                 # fault-free ticks after each fault (recovery)
FORGED_DUTY = 0.88              # the forged commands' duty (the issue's attack)
REPLAY_AGE_TICKS = 100          # a replayed command was recorded this many ticks earlier
SPAN_LEAD = REPLAY_AGE_TICKS + 50   # an injector's Python ticks before a window (Injector.spans)
SPAN_TAIL = 50                  # ... and after it
_HUB_DROPS = re.compile(r"\(read-only\): (\d+) frames it may not send dropped")


@dataclass(frozen=True)
class FaultSpec:
    name: str
    node: str          # whose path is faulty: plant (transmit), plant_rx, app, config
    ticks: int         # window length (bus faults)
    safety: bool       # safety-relevant: fail-safe within ``limit`` ticks
    expect: int        # ECU fault bits naming it (0: judged elsewhere)
    what: str
    limit: int = MAX_REACTION_TICKS   # ticks to the fail-safe state (or the fault bit)
    dtc: str = ""      # a plausible sensor fault: the DTC that isolates it (read over UDS;
    #                    "": detected, not isolated: the DTC read is reported, not claimed)
    plausible: bool = False           # a model-based detection (firmware.diag.fdi)


MAX_PLAUSIBLE_TICKS = 200       # plausible sensor faults: detected and fail-safe within 200 ms
MAX_ACTUATOR_TICKS = 20          # actuator and supply faults: within 20 ms
PLAUSIBLE_TICKS = 300            # their windows
PLAUSIBLE_GAP_TICKS = 4000       # and the fault-free time after each: the tester reads the
#                                  DTCs over UDS and clears them before the next one (the
#                                  bench runs on meanwhile: 2000 left too few ticks on vcan0
#                                  in UML once the compiled tick made it faster)
BIAS_COUNTS = 20                 # BA: 0.29 m/s^2 (the example); WA: 2.9 m/s^2; SWS 1 mm
GAIN = 1.5                       # around mid-scale
DRIFT_PER_S = {"ba": 2.0, "wa": 20.0, "defl": 0.01}   # m/s^2 per s, m/s^2 per s, m per s
STUCK_DUTY = 0.6                 # the bridge's PWM stuck at 60 % while enabled
SUPPLY_DROP = 0.6                # the supply falls to 60 % of nominal (28.8 V of 48 V)


def _plausible(name, what, dtc="", node="plant", expect=safety.FAULT_PLAUSIBILITY,
               limit=MAX_PLAUSIBLE_TICKS):
    return FaultSpec(name, node, PLAUSIBLE_TICKS, True, expect, what, limit=limit, dtc=dtc,
                     plausible=True)


def _actuator(name, what, dtc, expect=safety.FAULT_PLAUSIBILITY):
    """A fault of the plant's hardware (the bridge, the winding, the supply)."""
    return _plausible(name, what, dtc, node="plant_hw", expect=expect, limit=MAX_ACTUATOR_TICKS)


PLAUSIBLE = (
    _plausible("ba_bias", f"body accelerometer +{BIAS_COUNTS} counts (0.29 m/s^2)",
               "body_accel_plausibility"),
    _plausible("ba_drift", f"body accelerometer drifting {DRIFT_PER_S['ba']:g} m/s^2 per s"),
    _plausible("ba_gain", f"body accelerometer gain x{GAIN:g} around mid-scale"),
    _plausible("ba_stuck", "body accelerometer stuck at its last count", "body_accel_stuck"),
    _plausible("wa_bias", f"wheel accelerometer +{BIAS_COUNTS} counts (2.9 m/s^2)"),
    _plausible("wa_drift", f"wheel accelerometer drifting {DRIFT_PER_S['wa']:g} m/s^2 per s"),
    _plausible("wa_gain", f"wheel accelerometer gain x{GAIN:g} around mid-scale"),
    _plausible("wa_stuck", "wheel accelerometer stuck at its last count", "wheel_accel_stuck"),
    _plausible("defl_bias", f"deflection sensor +{BIAS_COUNTS} counts (1 mm)"),
    _plausible("defl_drift", f"deflection sensor drifting {DRIFT_PER_S['defl'] * 1e3:g} mm per s"),
    _plausible("defl_gain", f"deflection sensor gain x{GAIN:g} around mid-scale"),
    _plausible("defl_stuck", "deflection sensor stuck at its last count", "susp_defl_stuck"),
    _plausible("current_stuck", "motor current sensor stuck at mid-scale (0 A)",
               "motor_current_stuck"),
    _actuator("stuck_duty", f"the bridge's PWM stuck at {STUCK_DUTY:.0%} duty while enabled",
              "actuator_stuck"),
    _actuator("open_winding", "the motor winding open: no current flows", "actuator_open"),
    _actuator("supply_drop", f"the supply voltage falls to {SUPPLY_DROP:.0%} of nominal",
              "supply_voltage_low", expect=safety.FAULT_SUPPLY),
)
_SENSOR_SIGNAL = {"ba": "BODY_ACCEL_RAW", "wa": "WHEEL_ACCEL_RAW", "defl": "SUSP_DEFL_RAW",
                  "current": "MOTOR_CURRENT_RAW"}

FAULTS = (
    FaultSpec("sensor_loss_single", "plant", 1, True, safety.FAULT_TIMEOUT,
              "one PLANT_SENSORS frame lost"),
    FaultSpec("sensor_loss_burst", "plant", 50, True, safety.FAULT_TIMEOUT,
              "50 consecutive PLANT_SENSORS frames lost"),
    FaultSpec("bus_silence", "plant", 300, True, safety.FAULT_TIMEOUT,
              "the plant sends nothing for 300 ms"),
    FaultSpec("checksum", "plant", 5, True, safety.FAULT_CHECKSUM,
              "5 PLANT_SENSORS frames with a corrupted CHECKSUM"),
    FaultSpec("counter_repeat", "plant", 1, True, safety.FAULT_COUNTER,
              "PLANT_SENSORS repeats its COUNTER once"),
    FaultSpec("counter_jump", "plant", 1, True, safety.FAULT_COUNTER,
              "PLANT_SENSORS skips 5 COUNTER values"),
    FaultSpec("wrong_dlc", "plant", 5, True, safety.FAULT_DLC,
              "5 PLANT_SENSORS frames with DLC 7 instead of 8"),
    FaultSpec("unknown_id", "plant", 20, False, safety.FAULT_UNKNOWN_ID,
              f"a frame with the unknown ID 0x{UNKNOWN_FRAME_ID:X} every tick for 20 ms"),
    FaultSpec("out_of_range", "plant", 50, True, safety.FAULT_RANGE,
              "VEHICLE_SPEED reports 75 m/s (declared range 0-70) for 50 ms"),
    FaultSpec("adc_stuck_rail", "plant", 100, True, adc.FAULT_BIT["body_accel"],
              "body accelerometer stuck at the upper rail (4095 counts) for 100 ms"),
    FaultSpec("actuator_cmd_loss", "plant_rx", 100, True, 0,
              "the plant receives no ACTUATOR_CMD for 100 ms (must fall back to passive)"),
    FaultSpec("bus_flood", "plant", 100, False, safety.FAULT_RATE,
              "the plant sends VEHICLE_SPEED every tick (10x its rate) for 100 ms"),
    FaultSpec("driver_request_spam", "app", 1000, False, safety.FAULT_RATE,
              "the app sends a new mode request with every answer (10 per second) for 1 s"),
    FaultSpec("invalid_mode", "app", 100, False, safety.FAULT_INVALID_REQUEST,
              f"the app chooses mode {INVALID_MODE} (there are 5)"),
    FaultSpec("forged_cmd", "plant_rx", 50, True, 0,
              "an ACTUATOR_CMD forged without the key (valid CRC and COUNTER, 88 % duty) "
              "reaches the plant before every real one for 50 ms"),
    FaultSpec("replayed_cmd", "plant_rx", 50, True, 0,
              f"the ACTUATOR_CMD of {REPLAY_AGE_TICKS} ticks earlier is replayed to the plant "
              "before every real one for 50 ms"),
    *PLAUSIBLE,
    FaultSpec("external_sender", "bus", 50, True, 0,
              "an outside bus client sends a forged ACTUATOR_CMD with every tick for 50 ms"),
    FaultSpec("hub_message", "bus", 1, False, 0,
              "an outside client sends the hub a malformed frame (DLC 300)"),
    FaultSpec("config_nan", "config", 0, True, 0, "vehicle file with sprung_mass_kg = nan"),
    FaultSpec("config_inf", "config", 0, True, 0,
              "vehicle file with torque_constant_nm_per_a = inf"),
    FaultSpec("gains_nan", "config", 0, True, 0, "GA-LQR gains file with a NaN gain"),
)
BY_NAME = {f.name: f for f in FAULTS}
NOTES = {
    "actuator_cmd_loss": "judged by the plant: passive fallback (the ECU's actuator test "
                         "sees the current stop, as for an open winding)",
    "driver_request_spam": "the burst's first request is a valid one; the next, one answer "
                           "(100 ms) later, is the first too soon",
}


@dataclass(frozen=True)
class Window:
    name: str
    node: str
    start: int
    ticks: int


def schedule(names: Optional[list[str]] = None, warmup: int = 1500,
             gap: int = GAP_TICKS, bus: bool = True) -> list[Window]:
    """The bus faults one after the other: a warm-up (estimator and grade settle), then each
    fault's window followed by a fault-free gap (recovery). ``bus=False``: without the faults
    of an outside bus client (in one process there is no bus to attach to; they come last,
    so the other windows stay where they are)."""
    out, k = [], warmup
    for f in FAULTS:
        if f.node == "config" or (names is not None and f.name not in names) or (
                f.node == "bus" and not bus):
            continue
        out.append(Window(f.name, f.node, k, f.ticks))
        k += f.ticks + (PLAUSIBLE_GAP_TICKS if f.plausible else gap)
    return out


def campaign_ticks(windows: list[Window], gap: int = GAP_TICKS) -> int:
    if not windows:
        return 0
    last = windows[-1]
    return last.start + last.ticks + (PLAUSIBLE_GAP_TICKS if BY_NAME[last.name].plausible
                                      else gap)


class Injector:
    """Applies the windows of one node (``plant`` or ``app``) to its frames. ``applied``
    records, per fault, [first tick, last tick, frames touched]."""

    def __init__(self, windows: list[Window], node: str, lockstep: bool = True):
        nodes = ("plant", "plant_rx", "plant_hw") if node == "plant" else (node,)
        self.windows = [w for w in windows if w.node in nodes]
        self.lockstep = lockstep
        self.applied: dict[str, list[int]] = {}
        self._speed_raw: Optional[dict] = None
        self._spam_i = 0
        self._cmds: deque = deque(maxlen=REPLAY_AGE_TICKS)   # the last real commands
        self._held: dict = {}                                # stuck sensors' counts

    @classmethod
    def from_file(cls, path: str, node: str, lockstep: bool = True) -> "Injector":
        data = json.loads(Path(path).read_text())
        return cls([Window(**w) for w in data["windows"]], node, lockstep)

    def spans(self) -> list[tuple[int, int]]:
        """The ticks [start, end) this injector needs the Python nodes for (the compiled SIL
        loop runs the rest, ``hil.fastsil``): each window, from ``SPAN_LEAD`` ticks before it
        (what it watches before: the commands a replay takes, the last VEHICLE_SPEED a
        flood repeats) to ``SPAN_TAIL`` after (the app's time, from ECU_STATUS, lags the
        plant's by up to a status period; the supply is set back the tick after)."""
        return [(max(0, w.start - SPAN_LEAD), w.start + w.ticks + SPAN_TAIL)
                for w in self.windows]

    def _active(self, k: int, node: str) -> Optional[Window]:
        for w in self.windows:
            if w.node == node and w.start <= k < w.start + w.ticks:
                return w
        return None

    def _mark(self, name: str, k: int, n: int = 1) -> None:
        a = self.applied.setdefault(name, [k, k, 0])
        a[1] = k
        a[2] += n

    # -- plant: transmit -----------------------------------------------------------------------

    def before_emit(self, plant) -> None:
        w = self._active(plant.k, "plant")
        if w is None or w.name not in ("counter_repeat", "counter_jump"):
            return
        c = plant.tx.counters.get("PLANT_SENSORS", 0)
        step = -1 if w.name == "counter_repeat" else 5
        plant.tx.counters["PLANT_SENSORS"] = (c + step) & 0xF
        self._mark(w.name, plant.k)

    def after_emit(self, plant, frames: list[Frame]) -> list[Frame]:
        k = plant.k
        codec = plant.codec
        for fid, data in frames:
            if fid == ID["VEHICLE_SPEED"]:
                self._speed_raw = codec.decode(fid, data, scaling=False).signals
        w = self._active(k, "plant")
        if w is None or w.name in ("counter_repeat", "counter_jump"):
            return frames
        name = w.name
        sensors = ID["PLANT_SENSORS"]
        out = list(frames)
        if name in ("sensor_loss_single", "sensor_loss_burst", "bus_silence"):
            dropped = [f for f in out if name == "bus_silence" or f[0] == sensors]
            out = [f for f in out if f not in dropped]
            for fid, _ in dropped:
                plant.tx.sent[_name_of(codec, fid)] -= 1
            if self.lockstep:   # the ECU's timer still ticks: say so on the simulated bus
                out.append(plant.tx.frame("SIM_TICK", {"TICK": k & 0xFF}))
            self._mark(name, k, len(dropped))
        elif name == "checksum":
            fid, data = out[-1]
            cb = codec.specs[sensors].checksum_byte
            out[-1] = (fid, data[:cb] + bytes([data[cb] ^ 0x5A]) + data[cb + 1:])
            self._mark(name, k)
        elif name == "wrong_dlc":
            fid, data = out[-1]
            out[-1] = (fid, data[:-1])
            self._mark(name, k)
        elif name == "adc_stuck_rail":
            out[-1] = _reencode(codec, out[-1], BODY_ACCEL_RAW=4095)
            self._mark(name, k)
        elif BY_NAME[name].plausible:
            out[-1] = self._sensor_fault(codec, out[-1], name, k - w.start)
            self._mark(name, k)
        elif name == "out_of_range":
            for i, f in enumerate(out):
                if f[0] == ID["VEHICLE_SPEED"]:
                    out[i] = _reencode(codec, f, SPEED=OUT_OF_RANGE_SPEED_RAW)
                    self._mark(name, k)
        elif name == "unknown_id":
            out.insert(len(out) - 1, (UNKNOWN_FRAME_ID, bytes(range(8))))
            plant.tx.sent[f"0x{UNKNOWN_FRAME_ID:X}"] += 1
            self._mark(name, k)
        elif name == "bus_flood":
            if not any(f[0] == ID["VEHICLE_SPEED"] for f in out) and self._speed_raw:
                out.insert(0, plant.tx.frame("VEHICLE_SPEED", self._speed_raw))
                self._mark(name, k)
        return out

    def _sensor_fault(self, codec, frame: Frame, name: str, t: int) -> Frame:
        """A plausible sensor fault on the PLANT_SENSORS frame (``t``: ticks into it)."""
        channel, kind = name.rsplit("_", 1)
        sig = _SENSOR_SIGNAL[channel]
        raw = codec.decode(frame[0], frame[1], scaling=False).signals[sig]
        full = int(codec.message("PLANT_SENSORS").get_signal_by_name(sig).maximum)
        mid = (full + 1) // 2
        if kind == "bias":
            v = raw + BIAS_COUNTS
        elif kind == "gain":
            v = mid + round(GAIN * (raw - mid))
        elif kind == "drift":
            from hil.config import default_vehicle     # (the campaign's car)

            cfg = default_vehicle()
            ch = getattr(cfg.sensors, {"ba": "body_accel", "wa": "wheel_accel",
                                       "defl": "susp_defl"}[channel])
            v = raw + round(DRIFT_PER_S[channel] * t * cfg.sim.plant_dt_s / ch.lsb)
        elif channel == "current":
            v = mid                               # (0 A: the range is symmetric)
        else:                                     # stuck at the first count of the window
            v = self._held.setdefault(name, raw)
        return _reencode(codec, frame, **{sig: min(full, max(0, int(v)))})

    # -- plant: its hardware -------------------------------------------------------------------

    def hardware(self, plant, duty: int, regen: bool, enable: bool) -> tuple[int, bool, bool]:
        """The bridge, the winding and the supply as they are this tick: the command the
        corner actually gets (``plant.k``), and the supply voltage set on the plant."""
        w = self._active(plant.k, "plant_hw")
        nominal = plant.cfg.actuator.bus_voltage_v
        plant.active.set_bus_voltage(nominal * SUPPLY_DROP if w is not None
                                     and w.name == "supply_drop" else nominal)
        if w is None:
            return duty, regen, enable
        self._mark(w.name, plant.k)
        if w.name == "stuck_duty" and enable:
            duty = round(STUCK_DUTY * 32768)
        elif w.name == "open_winding":
            enable = False            # (the winding carries no current: an open bridge's)
        return duty, regen, enable

    # -- plant: receive ------------------------------------------------------------------------

    def drop_rx(self, plant, fid: int) -> bool:
        w = self._active(plant.k, "plant_rx")
        if w is not None and w.name == "actuator_cmd_loss" and fid == ID["ACTUATOR_CMD"]:
            self._mark(w.name, plant.k)
            return True
        return False

    def rx_extra(self, plant, data: bytes) -> list[bytes]:
        """Commands an attacker slips in before the real one (``data``): forged without the
        key, or replayed from ``REPLAY_AGE_TICKS`` earlier. Records the real ones."""
        self._cmds.append(data)
        w = self._active(plant.k, "plant_rx")
        if w is None or w.name not in ("forged_cmd", "replayed_cmd"):
            return []
        self._mark(w.name, plant.k)
        if w.name == "replayed_cmd":
            return [self._cmds[0]]
        return [forged_command(plant.codec, (plant.cmd_rx.last_counter + 1) & 0xF,
                               (plant.tx.counters.get("PLANT_SENSORS", 0) - 1) & 0x3,
                               plant.k)]

    # -- app: before it answers a MODE_RECOMMEND ------------------------------------------------

    def before_answer(self, app) -> None:
        w = self._active(app.t, "app")
        if w is None:
            return
        if w.name == "driver_request_spam":
            # a new request with every answer; the first asks for the mode in use
            i = self._spam_i
            self._spam_i += 1
            mode = fp.MODE_COMFORT if i % 2 == 0 else fp.MODE_COMPREHENSIVE
            app._send(fp.REQ_CHOOSE, mode)
            self._mark(w.name, app.t)
        elif w.name == "invalid_mode" and w.name not in self.applied:
            app._send(fp.REQ_CHOOSE, INVALID_MODE)
            self._mark(w.name, app.t)


def forged_command(codec, counter: int, seq: int, salt: int) -> bytes:
    """An ACTUATOR_CMD as an attacker with the DBC but without the key builds it: 88 % duty,
    bridge enabled, the right SENSOR_SEQ, the COUNTER the receiver expects, a valid CRC, and
    MAC and freshness bytes that are a guess."""
    return codec.encode("ACTUATOR_CMD", {
        "DUTY": FORGED_DUTY, "REGEN": 0, "ENABLE": 1, "SENSOR_SEQ": seq,
        "FRESHNESS": salt & 0xFF, "MAC": (salt * 2654435761) & 0xFFFFFF}, counter)


def _name_of(codec, fid: int) -> str:
    return codec.db.get_message_by_frame_id(fid).name


def _reencode(codec, frame: Frame, **raw_over) -> Frame:
    """The same frame with some raw signal values replaced, COUNTER kept, CHECKSUM resealed
    (a sensor or sender fault, not a transmission error)."""
    fid, data = frame
    name = _name_of(codec, fid)
    raw = dict(codec.decode(fid, data, scaling=False).signals)
    raw.update(raw_over)
    return fid, codec.encode_raw(name, raw, raw.get("COUNTER", 0))


# -- judging ----------------------------------------------------------------------------------

@dataclass
class Result:
    fault: str
    detected: bool
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
    isolated: Optional[bool] = None   # the DTC naming the faulty channel confirmed (None:
    #                                   not claimed for this fault)
    snapshot_ok: Optional[bool] = None  # its snapshot: in the window, the drive's speed


def judge(windows: list[Window], ecu_tr: dict, plant_tr: dict, applied: dict,
          faults_seen: list, ticks_run: int, crash: Optional[str], mode: int,
          hub_log: str = "", dtcs: Optional[dict] = None) -> list[Result]:
    """Per bus fault: read the ECU's and the plant's per-tick records around its window (and
    the hub's log, for an outside client's frames)."""
    faults = np.asarray(ecu_tr["faults"], dtype=np.int64)
    enable = np.asarray(ecu_tr["enable"], dtype=bool)
    modes = np.asarray(ecu_tr["mode"])
    fallback = np.asarray(plant_tr["fallback"], dtype=bool)
    n = min(len(faults), len(fallback))
    out = []
    for i, w in enumerate(windows):
        spec = BY_NAME[w.name]
        end = windows[i + 1].start if i + 1 < len(windows) else n
        crashed = crash is not None and ticks_run < end
        a = applied.get(w.name)
        if a is None or a[0] >= n:
            out.append(Result(w.name, False, None, False, crashed, spec.safety,
                              note="not injected" if a is None else "run ended first"))
            continue
        first, last = a[0], a[1]
        seg = slice(first, end)
        if w.name in ATTACKS:
            out.append(_judge_attack(w, a, seg, plant_tr, enable, fallback, crashed, hub_log))
            continue
        if spec.node == "plant_rx":
            hit = np.flatnonzero(fallback[seg])
            bad = fallback[seg]
            bits = []
        else:
            hit = np.flatnonzero(~enable[seg] if spec.safety else (faults[seg] & spec.expect))
            if spec.safety:   # detected means named too, not only disabled
                hit = hit if np.any(faults[seg] & spec.expect) else hit[:0]
            bad = (faults[seg] != 0) | ~enable[seg]
            bits = safety.fault_names(int(np.bitwise_or.reduce(faults[seg])))
        detected = hit.size > 0
        reaction = int(hit[0]) if detected else None
        bad_idx = np.flatnonzero(bad)
        last_bad = first + int(bad_idx[-1]) if bad_idx.size else last
        recovered = bool(detected and last_bad < end - 1)
        told = None
        if spec.expect:
            told = any(first <= t < end and f & spec.expect for t, f, _ in faults_seen)
        kept = None
        if spec.node == "app":
            kept = bool(np.all((modes[seg] == mode) | (modes[seg] == fp.MODE_PASSIVE)))
        r = Result(
            w.name, detected, reaction, recovered, crashed, spec.safety,
            recovery_ticks=max(0, last_bad - last) if recovered else None, driver_told=told,
            fault_bits=bits, failsafe_ticks=int(np.count_nonzero(~enable[seg])),
            mode_kept=kept, note=NOTES.get(w.name, ""))
        if spec.plausible:
            _judge_dtc(r, spec, first, w, (dtcs or {}).get(w.name))
        out.append(r)
    return out


SNAPSHOT_SPEED_TOL_MPS = 0.2


def _judge_dtc(r: Result, spec: FaultSpec, first: int, w: Window, read: Optional[dict]) -> None:
    """A plausible fault's DTCs as the tester read them over UDS after its window: its
    model-based DTCs confirmed, each with a snapshot taken inside the window at the drive's
    speed; ``isolated``: the DTC naming the faulty channel is among them (where the fault
    claims it)."""
    from hil.config import default_vehicle

    dt_ms = default_vehicle().sim.plant_dt_s * 1e3
    r.detect_ms = None if r.reaction_ticks is None else r.reaction_ticks * dt_ms
    if read is None or "error" in read:
        r.dtc = []
        r.note = (read or {}).get("error", "the DTCs were not read")
        r.snapshot_ok = False
        r.isolated = False if spec.dtc else None
        return
    from firmware.diag import dtc as fw

    got = [d for d in read["dtcs"] if d["status"] & 0x08]          # confirmed
    r.dtc = [f"{d['code']} {d['name']}" for d in got]
    # the fault's own DTCs are the model-based ones; a frame DTC beside them (bus_rate: the
    # driver app's request at the mode swap when the fail-safe ends) may fall after the window
    own = [d for d in got if fw.DTCS[fw.BY_NAME[d["name"]]].source == fw.SRC_TEST]
    r.snapshot_ok = bool(own) and all(
        "snapshot" in d and first <= d["snapshot"]["tick"] < w.start + w.ticks
        and d["snapshot"]["speed_mps"] is not None
        and abs(d["snapshot"]["speed_mps"] - CAMPAIGN_SPEED_MPS) <= SNAPSHOT_SPEED_TOL_MPS
        for d in own)
    if spec.dtc:
        r.isolated = any(d["name"] == spec.dtc for d in own)


ATTACKS = ("forged_cmd", "replayed_cmd", "external_sender", "hub_message")


def _judge_attack(w: Window, a: list, seg: slice, plant_tr: dict, enable, fallback,
                  crashed: bool, hub_log: str) -> Result:
    """An attack is detected when every frame of it was stopped (dropped by the hub, or
    rejected by the plant's SecOC check) and recovered when it had no effect at all: no
    passive fallback and no fail-safe tick in its window. A malformed hub message is
    detected when the hub disconnected its sender, recovered when the run went on."""
    sent = a[2]
    if w.name == "hub_message":
        hit = "disconnecting" in hub_log and "dlc 300" in hub_log
        return Result(w.name, hit, 0 if hit else None, hit and not crashed, crashed, False,
                      note="the hub disconnected the client" if hit else "not in hub.log")
    rejected = np.asarray(plant_tr.get("rejected", np.zeros(0)))
    stopped = int(rejected[seg].sum()) if w.name != "external_sender" else int(
        rejected[seg.start:].sum())
    note = f"{stopped} of {sent} rejected by the plant's SecOC check"
    if w.name == "external_sender" and hub_log:         # (vcan0: no hub, no hub.log)
        dropped = sum(int(x) for x in _HUB_DROPS.findall(hub_log))
        stopped += dropped
        note = f"{dropped} of {sent} dropped at the hub (read-only client), " + note
    hit = sent > 0 and stopped >= sent
    clean = not np.any(fallback[seg]) and bool(np.all(enable[seg]))
    return Result(w.name, hit, 0 if hit else None, hit and clean, crashed, True,
                  recovery_ticks=0 if hit and clean else None, fault_bits=[],
                  failsafe_ticks=int(np.count_nonzero(~enable[seg])), note=note)


def _attacker(windows: list[Window], spec, marks: dict, stop, on_bus: dict) -> None:
    """The campaign's outside bus client: read-only (no credentials), it counts the plant's
    ticks from the bus and, in its windows, sends a forged ACTUATOR_CMD with every tick
    (``external_sender``) or a malformed message to the hub (``hub_message``). ``on_bus``
    counts the frames it put on the bus itself (vcan0: no hub drops them), so the run's
    check of frames on the bus against frames sent counts them too."""
    import can

    from hil.codec import Codec

    codec = Codec()
    mine = [w for w in windows if w.node == "bus"]
    if spec.interface != "remote":
        mine = [w for w in mine if w.name != "hub_message"]
    if not mine:
        return
    ticks_ids = [{"can_id": ID[n], "can_mask": 0x7FF, "extended": False}
                 for n in ("PLANT_SENSORS", "SIM_TICK")]
    bus = spec.open(can_filters=ticks_ids)
    k = -1                  # the plant's tick of the last tick frame seen (the first is tick 0)
    try:
        while not stop.is_set() and mine:
            msg = bus.recv(0.2)
            if msg is None:
                continue
            k += 1
            w = mine[0]
            if k < w.start:
                continue
            if k >= w.start + w.ticks:
                mine.pop(0)
                continue
            a = marks.setdefault(w.name, [k, k, 0])
            a[1], a[2] = k, a[2] + 1
            if w.name == "external_sender":
                bus.send(can.Message(arbitration_id=ID["ACTUATOR_CMD"], is_extended_id=False,
                                     data=forged_command(codec, k & 0xF, k & 0x3, k)))
                if spec.interface != "remote":
                    on_bus["ACTUATOR_CMD"] = on_bus.get("ACTUATOR_CMD", 0) + 1
            else:
                _malformed_hub_message(spec.channel)
                mine.pop(0)
    finally:
        from hil.bus import close_bus

        close_bus(bus)


DTC_READ_AFTER = 1000           # ticks after a plausible fault's window: its DTCs are read
DTC_CLEAR_BEFORE = 300          # ... and before the first one, the DTCs of the earlier faults
#                                 are cleared (so each snapshot is the fault's own)


def _read_points(windows: list[Window]) -> list[tuple[int, Optional[Window]]]:
    """(tick, window) of the tester's reads, each followed by a clear; window None: a clear
    before the first plausible fault."""
    points = [(w.start + w.ticks + DTC_READ_AFTER, w) for w in windows
              if BY_NAME[w.name].plausible]
    if points:
        first = next(w for w in windows if BY_NAME[w.name].plausible)
        points.insert(0, (max(0, first.start - DTC_CLEAR_BEFORE), None))
    return points


def _tester(windows: list[Window], spec, out: Path, reads: dict, stop) -> None:
    """The campaign's UDS tester: udsoncan over can-isotp, as ``python -m hil diag`` (on a hub
    authenticated as TESTER with the run's hub.secret). It counts the plant's ticks from the
    bus; ``DTC_READ_AFTER`` ticks after each plausible fault's window it reads the DTCs
    (status, snapshot, extended data) and clears them, and says so when the read was not
    over before the next fault began; ``DTC_CLEAR_BEFORE`` ticks before the first one it
    only clears (one exchange: reading the earlier faults' DTCs first took longer than those
    ticks on vcan0 in UML, and the late clear wiped the first fault's own)."""
    points = _read_points(windows)
    if not points:
        return
    from hil import diag
    from hil.bus import close_bus
    from hil.secoc import load_key

    ticks = bus = None
    try:
        ticks = spec.open(can_filters=[{"can_id": ID[n], "can_mask": 0x7FF, "extended": False}
                                       for n in ("PLANT_SENSORS", "SIM_TICK")])
        bus = diag.tester_bus(spec, load_key(out / "hub.secret")
                              if spec.interface == "remote" else None)
        with diag.client(bus, timeout=2.0) as client:
            k = -1
            late_clear: dict = {}      # fault -> the tick the clear before it ended, late
            while not stop.is_set() and points:
                msg = ticks.recv(0.2)
                if msg is None:
                    continue
                k += 1
                if k == 0:
                    # the first exchange sets up both ISO-TP stacks (the ECU node imports
                    # its own on the first request): here, long before the first read, not
                    # in a read's time (on vcan0 in UML it took longer than the 300 ticks
                    # between the first clear and the fault after it)
                    try:
                        client.tester_present()
                    except Exception:  # noqa: BLE001 - the reads below say what fails
                        pass
                    while ticks.recv(0) is not None:
                        k += 1
                    continue
                at, w = points[0]
                if k < at:
                    continue
                points.pop(0)
                try:
                    if w is None:       # (the clear before the first fault: one exchange)
                        client.clear_dtc(0xFFFFFF)
                        doc = {"dtcs": [], "cleared": True}
                    else:
                        doc = diag.read_dtcs(client, clear=True)
                except Exception as exc:  # noqa: BLE001 - a failed read is a finding
                    doc = {"error": f"UDS read failed: {type(exc).__name__}: {exc}"}
                while ticks.recv(0) is not None:       # the ticks that passed meanwhile
                    k += 1
                later = [x for x in windows if x.start >= at]
                if later and k >= later[0].start and "error" not in doc:
                    doc = {"error": f"the read ended at tick {k}, after the next fault began"}
                    if w is None:          # a late clear may have wiped the next fault's DTCs
                        late_clear[later[0].name] = k
                if w is not None and w.name in late_clear and "error" not in doc:
                    doc = {"error": f"the clear before this fault ended at tick "
                                    f"{late_clear[w.name]}, after it began"}
                reads[w.name if w else "(clear)"] = doc
    except Exception as exc:  # noqa: BLE001 - the tester could not work: every read says so
        for _, w in points:
            reads.setdefault(w.name if w else "(clear)",
                             {"error": f"the UDS tester failed: {type(exc).__name__}: {exc}"})
    finally:
        for b in (ticks, bus):
            if b is not None:
                close_bus(b)


def _read_memory(node) -> dict:
    """In process (no bus): the DTCs straight from the ECU's memory, as the tester reports
    them, then cleared (``--in-process`` only; the bus campaign reads them over UDS)."""
    from firmware.diag import dtc as fw
    from hil.diag import dtc_label

    out = []
    for i, e in enumerate(node.state.diag.dtc.entries):
        if e.status & 0x2F:
            d = fw.DTCS[i]
            snap = e.snapshot
            out.append({"code": dtc_label(d.code), "name": d.name, "status": e.status,
                        **({"snapshot": {"tick": snap.tick, "speed_mps": None
                                         if snap.speed_cmps == 0xFFFF else snap.speed_cmps / 100}}
                           if snap else {})})
    fw.clear(node.state.diag.dtc, 0xFFFFFF)
    return {"dtcs": out}


def _malformed_hub_message(url: str) -> None:
    """A client that opens a WebSocket to the hub and sends a frame with DLC 300."""
    import socket
    from urllib.parse import urlparse

    from hil import wsframe

    u = urlparse(url)
    with socket.create_connection((u.hostname, u.port), timeout=2.0) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: "
                     b"Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                     b"Sec-WebSocket-Protocol: can.json.v1\r\n\r\n")
        for event in ({"type": "bus_request", "payload": {"config": {}}},
                      {"type": "message", "payload": {"arbitration_id": ID["ACTUATOR_CMD"],
                                                      "dlc": 300, "data": [1]}}):
            sock.sendall(wsframe.frame(wsframe.TEXT, json.dumps(event).encode()))
        try:
            while sock.recv(4096):
                pass
        except OSError:
            pass


def config_faults(out: Path, names: Optional[list[str]] = None) -> list[Result]:
    """Start the ECU node with a broken configuration file: it must refuse with a one-line
    error (exit code 2) before it touches the bus, never with a traceback."""
    from hil.config import DEFAULT_VEHICLE_FILE

    out.mkdir(parents=True, exist_ok=True)
    text = DEFAULT_VEHICLE_FILE.read_text()
    cases = {
        "config_nan": (["--vehicle"], "vehicle_nan.toml",
                       _set_key(text, "sprung_mass_kg", "nan"), "sprung_mass_kg"),
        "config_inf": (["--vehicle"], "vehicle_inf.toml",
                       _set_key(text, "torque_constant_nm_per_a", "inf"), "torque_constant_nm_per_a"),
        "gains_nan": (["--gains"], "gains_nan.json",
                      '{"K": [NaN, 1.0, 2.0, 3.0, 4.0]}\n', "K"),
    }
    results = []
    for name, (flag, fname, body, key) in cases.items():
        if names is not None and name not in names:
            continue
        path = out / fname
        path.write_text(body)
        proc = subprocess.run([sys.executable, "-m", "hil", "ecu", *flag, str(path),
                               "--out", str(out / "config_run")],
                              capture_output=True, text=True, timeout=120,
                              stdin=subprocess.DEVNULL)
        err = proc.stderr.strip()
        crashed = "Traceback" in proc.stderr or proc.returncode not in (0, 2)
        detected = proc.returncode == 2 and key in err and len(err.splitlines()) == 1
        results.append(Result(name, detected, 0 if detected else None, None, crashed, True,
                              note=err.splitlines()[-1] if err else f"exit {proc.returncode}"))
    return results


def _set_key(text: str, key: str, value: str) -> str:
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.split("=")[0].strip() == key:
            lines[i] = f"{key} = {value}"
            return "\n".join(lines) + "\n"
    raise KeyError(key)


# -- running ----------------------------------------------------------------------------------

def _route_file(out: Path, ticks: int, dt: float) -> Path:
    length = CAMPAIGN_SPEED_MPS * (ticks * dt + 1.0)
    path = out / "route.toml"
    path.write_text(f'name = "faults"\ndescription = "fault campaign: grade {CAMPAIGN_GRADE} '
                    f'at {CAMPAIGN_SPEED_MPS:g} m/s"\n\n[[segment]]\ngrade = "{CAMPAIGN_GRADE}"\n'
                    f"length_m = {length:.1f}\nspeed_mps = {CAMPAIGN_SPEED_MPS:g}\n")
    return path


def run_in_process(windows: list[Window], out: Path, seed: int = 1,
                   compiled: bool = True) -> dict:
    """The campaign with the three nodes in this process (the lockstep FIFO): the compiled
    SIL loop between the windows (``hil.fastsil``; the node objects in them and at the
    tester's reads), or (``compiled=False``) the node objects throughout."""
    from hil import fastsil, nodes, secoc
    from hil.codec import Codec
    from hil.config import default_vehicle
    from hil.road import load_route
    from hil.sil import app_node, ecu_params

    cfg = default_vehicle()
    dt = cfg.sim.plant_dt_s
    n = campaign_ticks(windows)
    route = load_route(_route_file(out, n, dt))
    codec = Codec()
    key = secoc.new_key()
    plant = nodes.PlantNode(cfg, route, seed, codec, inject=Injector(windows, "plant"),
                            key=key)
    plant.n = min(plant.n, n)
    ecu_node = nodes.EcuNode(ecu_params(cfg, CAMPAIGN_MODE), codec, key=key)
    app = app_node(codec, CAMPAIGN_MODE, dt, key=key)
    app.inject = Injector(windows, "app")
    points, reads, tick = _read_points(windows), {}, ecu_node.tick

    def ticking():
        while points and ecu_node.k >= points[0][0]:
            w = points.pop(0)[1]
            reads[w.name if w else "(clear)"] = _read_memory(ecu_node)
        return tick()

    ecu_node.tick = ticking
    crash = None
    try:
        if compiled:
            fastsil.run(plant, ecu_node, app, python=[(k, k + 1) for k, _ in points])
        else:
            nodes.run_in_process(plant, ecu_node, app)
    except Exception as exc:  # noqa: BLE001 - a crash is a finding, reported per fault
        crash = f"{type(exc).__name__}: {exc}"
    return {"ecu": ecu_node.trace(), "plant": plant.trace(),
            "applied": {**plant.inject.applied, **app.inject.applied},
            "faults_seen": app.faults_seen, "ticks": ecu_node.k, "crash": crash,
            "dtcs": reads, "summaries": [node.summary() for node in (plant, ecu_node, app)]}


def run_over_bus(windows: list[Window], out: Path, seed: int = 1,
                 interface: Optional[str] = None, channel: Optional[str] = None) -> dict:
    """The campaign as ``hil run --pace lockstep`` with the injector in the plant and app
    processes (``--inject``); a node that dies or prints a traceback is a crash."""
    from hil import supervisor
    from hil.config import default_vehicle

    dt = default_vehicle().sim.plant_dt_s
    n = campaign_ticks(windows)
    plan = out / "plan.json"
    plan.write_text(json.dumps({"windows": [asdict(w) for w in windows]}, indent=1) + "\n")
    args = argparse.Namespace(
        route=str(_route_file(out, n, dt)), mode=CAMPAIGN_MODE, controller=None, seed=seed,
        gains=None, design=None, duration=n * dt, out=str(out), pace="lockstep", json=False,
        vehicle=None,
        driver=None, script=None, fixed_point=False, interface=interface, channel=channel,
        inject=str(plan), key_file=None, outside_frames={})
    marks: dict = {}
    reads: dict = {}
    stop = threading.Event()
    threads: list = []

    def attach(spec):                 # the outside clients, once the bus is up
        for target, extra in ((_attacker, (windows, spec, marks, stop, args.outside_frames)),
                              (_tester, (windows, spec, out, reads, stop))):
            t = threading.Thread(target=target, args=extra, daemon=True)
            t.start()
            threads.append(t)

    with contextlib.redirect_stdout(sys.stderr):
        code = supervisor.run(args, on_bus=attach)
    stop.set()
    for t in threads:
        t.join(5.0)
    crash = None if code == 0 else f"hil run exited with code {code}"
    for name in supervisor.NODES:
        log = out / f"{name}.log"
        if log.exists() and "Traceback" in log.read_text(errors="replace"):
            crash = f"node {name} printed a traceback (see {log})"
    try:
        ecu_tr, plant_tr = dict(np.load(out / "ecu.npz")), dict(np.load(out / "plant.npz"))
        sums = {k: json.loads((out / f"{k}.json").read_text()) for k in ("plant", "app")}
    except (OSError, ValueError) as exc:
        return {"ecu": {"faults": [], "enable": [], "mode": []}, "plant": {"fallback": []},
                "applied": {}, "faults_seen": [], "ticks": 0,
                "crash": crash or f"no node records: {exc}"}
    hub_log = out / "hub.log"
    return {"ecu": ecu_tr, "plant": plant_tr,
            "applied": {**sums["plant"].get("injected", {}), **sums["app"].get("injected", {}),
                        **marks},
            "faults_seen": [tuple(e) for e in sums["app"]["faults_seen"]],
            "ticks": len(ecu_tr["faults"]), "crash": crash, "dtcs": reads,
            "hub_log": hub_log.read_text(errors="replace") if hub_log.exists() else ""}


def campaign(out: Path, *, in_process: bool = False, seed: int = 1,
             names: Optional[list[str]] = None, interface: Optional[str] = None,
             channel: Optional[str] = None) -> list[Result]:
    out.mkdir(parents=True, exist_ok=True)
    windows = schedule(names, bus=not in_process)
    if not in_process and not _on_hub(interface, channel):      # vcan0: no hub to attack
        windows = [w for w in windows if w.name != "hub_message"]
    results: list[Result] = []
    if windows:
        run = (run_in_process(windows, out, seed) if in_process
               else run_over_bus(windows, out, seed, interface, channel))
        results += judge(windows, run["ecu"], run["plant"], run["applied"],
                         run["faults_seen"], run["ticks"], run["crash"],
                         fp.MODE_COMFORT, run.get("hub_log", ""), run.get("dtcs"))
        if run["crash"]:
            print(f"faults: {run['crash']}", file=sys.stderr, flush=True)
    results += config_faults(out / "config", names)
    return results


def _on_hub(interface: Optional[str], channel: Optional[str]) -> bool:
    from hil.bus import BusError, resolve

    try:
        spec, needs_hub = resolve(interface, channel)
    except BusError:
        return True                   # (the run itself says what is wrong)
    return needs_hub or spec.interface == "remote"


def passed(results: list[Result]) -> bool:
    return all(_holds(r) for r in results)


def _holds(r: Result) -> bool:
    spec = BY_NAME[r.fault]
    return (r.detected and not r.crashed
            and (not r.safety_relevant or (r.reaction_ticks or 0) <= spec.limit)
            and r.recovered is not False
            and (not spec.plausible or (bool(r.dtc) and r.snapshot_ok
                                        and r.isolated is not False)))


def checks(results: list[Result]) -> list:
    """The verdict's checks: one per fault. Value: the reaction in ticks (or what went wrong);
    limit: what the fault must meet."""
    from hil.verdict import Check

    out = []
    for r in results:
        spec = BY_NAME[r.fault]
        limit = "detected" + (f", fail-safe within {spec.limit} ticks"
                              if r.safety_relevant else "")
        limit += ", recovered" if r.recovered is not None else ""
        if spec.plausible:
            limit += ", DTC confirmed with its snapshot" + (
                f", {spec.dtc}" if spec.dtc else "")
        if r.crashed:
            value = "crashed"
        elif not r.detected:
            value = "missed"
        elif r.recovered is False:
            value = f"reaction {r.reaction_ticks} ticks, not recovered"
        else:
            value = f"reaction {r.reaction_ticks} ticks"
        if spec.plausible:
            value += f"; DTC {', '.join(r.dtc or []) or 'none'}" + (
                "" if r.snapshot_ok else ", snapshot wrong or missing") + (
                ", not isolated" if r.isolated is False else "")
        out.append(Check(f"fault.{r.fault}", value, limit, _holds(r)))
    return out


def _table(results: list[Result]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"fault campaign: ECU in {CAMPAIGN_MODE} mode, grade {CAMPAIGN_GRADE} at "
                    f"{CAMPAIGN_SPEED_MPS:g} m/s, lockstep (ticks of 1 ms)")
    for col in ("fault", "safety", "detected", "reaction", "recovered", "recovery", "crashed",
                "driver told", "fault bits", "dtc", "detect_ms", "isolated"):
        t.add_column(col, no_wrap=True)

    def cell(v, bad=False):
        if v is None:
            return "-"
        if isinstance(v, bool):
            return ("yes" if v else "NO") if bad else ("yes" if v else "no")
        return str(v)

    for r in results:
        node = BY_NAME[r.fault].node
        bits = r.note if r.fault in ATTACKS else ", ".join(r.fault_bits or []) or {
            "config": "refused: exit 2, one-line error" if r.detected else r.note,
            "plant_rx": "(plant: passive fallback)"}.get(node, "")
        t.add_row(r.fault, cell(r.safety_relevant), cell(r.detected, True),
                  cell(r.reaction_ticks), cell(r.recovered, True), cell(r.recovery_ticks),
                  "YES" if r.crashed else "no", cell(r.driver_told, True), bits,
                  ", ".join(d.split()[0] for d in r.dtc) if r.dtc else "-",
                  cell(r.detect_ms), cell(r.isolated, True))
    console = Console()
    if not console.is_terminal:
        console = Console(width=200)
    console.print(t)


def main(args) -> int:
    names = None
    if args.only:
        names = [s.strip() for s in args.only.split(",") if s.strip()]
        unknown = sorted(set(names) - set(BY_NAME))
        if unknown:
            from hil.cli import fail

            fail(f"faults: unknown fault(s) {', '.join(unknown)} "
                 f"(known: {', '.join(BY_NAME)})")
    from hil.cli import lock_out

    lock_out(args.out)
    t0 = time.monotonic()
    results = campaign(Path(args.out), in_process=args.in_process, seed=args.seed, names=names,
                       interface=getattr(args, "interface", None),
                       channel=getattr(args, "channel", None))
    from hil import verdict

    doc = verdict.attach({"results": [asdict(r) for r in results]}, checks(results))
    (Path(args.out) / "faults.json").write_text(json.dumps(doc, indent=1) + "\n")
    if getattr(args, "junit", None):
        verdict.write_junit(args.junit, "hil faults", checks(results), time.monotonic() - t0)
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        _table(results)
        frame = [r for r in results if r.safety_relevant and not BY_NAME[r.fault].plausible]
        kinds = (("plausible sensor faults", MAX_PLAUSIBLE_TICKS),
                 ("actuator and supply faults", MAX_ACTUATOR_TICKS))
        model = "".join(
            f", {what} {max(r.reaction_ticks or 0 for r in rs)} ticks (limit {limit})"
            for what, limit in kinds
            for rs in [[r for r in results if BY_NAME[r.fault].plausible
                        and BY_NAME[r.fault].limit == limit]] if rs)
        print(f"{sum(r.detected for r in results)}/{len(results)} detected, "
              f"{sum(r.crashed for r in results)} crashed, max safety reaction "
              f"{max((r.reaction_ticks or 0) for r in frame) if frame else 0} ticks "
              f"(limit {MAX_REACTION_TICKS}){model}"
              f"; {time.monotonic() - t0:.1f} s; {Path(args.out) / 'faults.json'}")
        verdict.render(doc)
    return verdict.exit_code(doc)
