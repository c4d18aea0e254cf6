"""The bench's three CAN nodes as frame-driven state machines: no sockets, no clock.

``PlantNode`` (the simulator: road, quarter car, sensors, passive twin), ``EcuNode`` (the
firmware behind its receive/transmit path) and ``AppNode`` (the driver-app emulator) only
exchange ``(frame_id, payload)`` pairs encoded with the DBC. The same objects run in one
process (``hil sim``, :func:`run_in_process`) and as three processes on a CAN bus
(``hil run``, ``hil.bench.procs``), so the two harnesses compute the same thing by construction.

Lockstep protocol (deterministic, as fast as the bus allows), per tick k:
  1. the plant samples its sensors and sends, in this order, VEHICLE_SPEED, PLANT_SUPPLY and
     SIM_TRUTH (every 10 ms), ENERGY_STATUS (every 100 ms), PLANT_SENSORS (every tick);
  2. on PLANT_SENSORS the ECU steps once and sends ECU_STATUS and ECU_ESTIMATES (every 10 ms)
     and MODE_RECOMMEND (every 100 ms and on change);
  3. the app answers every MODE_RECOMMEND with exactly one DRIVER_REQUEST (a new request or
     the heartbeat repeating the last), which the ECU applies from tick k+1;
  4. the ECU sends ACTUATOR_CMD last: at once, or after that answer when it sent a
     MODE_RECOMMEND; the plant steps when the command is in.
Every frame is thus caused by the one before it, so the order on the bus is fixed and the
log of a lockstep run is the same bytes as ``hil sim``'s. Periods come from the DBC's
GenMsgCycleTime. In ``realtime`` pacing nobody waits: the ECU sends its command at once, the
plant steps on its 1 kHz clock with the latest valid command.
"""

from __future__ import annotations

import copy
import hashlib
import struct
from array import array
from collections import Counter, deque
from dataclasses import replace
from typing import Callable, Iterable, Optional

import numpy as np

from calib.fx_tables import build_tables
from firmware import safety
from firmware.diag import uds
from firmware.modes import REASON_NONE
from firmware import params as fp
from firmware.ecu import Ecu
from firmware.layout import view
from hil.transport import secoc
from hil.kernels import bus as kb
from hil.kernels import ecunode as ken
from hil.kernels import frames as kf
from hil.kernels import secoc as ks
from hil.kernels.cmac import Cmac
from hil.transport.codec import Codec, fault_word
from calib.vehicle import VehicleConfig
from hil.sim.drive import road_at_ticks
from hil.sim.plant import OBS, QuarterCarPlant
from hil.sim.road import GRADES, Route, drive_timeline, generate_profile
from hil.sim.sensors import SensorSuite, SupplySensor

Frame = tuple[int, bytes]

# message IDs (from the DBC, resolved once)
_DB = Codec()
ID = {m.name: m.frame_id for m in _DB.db.messages}
NAME_OF = {v: k for k, v in ID.items()}
OWNER = {m.name: (m.senders or [""])[0] for m in _DB.db.messages}
TWIN_CHUNK = 250                        # passive-twin ticks computed per batch

# PlantNode.obs columns after plant.OBS: the duty applied, the passive fallback, and the
# commands rejected by SecOC in that tick
_DUTY, _FALLBACK, _REJECTED = len(OBS), len(OBS) + 1, len(OBS) + 2
TRACE = ("ba", "sws", "dtd", "force", "p_ba", "p_sws", "p_dtd", "p_vrel", "stored", "drawn",
         "duty", "fallback", "rejected")       # the plant's trace columns
# What the trace hash takes per tick, in this order: the ECU's inputs, then its outputs, each
# packed little-endian with its struct code. The two "reserved" fields are always 0; they stay
# so that every recorded trace hash (tests/golden, earlier reports) stays valid.
HASHED = (
    ("tick", "q"), ("body_accel", "i"), ("wheel_accel", "i"), ("susp_defl", "i"),
    ("motor_current", "i"), ("speed", "i"), ("supply", "i"),   # counts as received, -1: none
    ("req_kind", "i"), ("req_mode", "i"), ("req_counter", "i"), ("link_faults", "I"),
    ("duty_q15", "i"), ("regen", "B"), ("enable", "B"), ("recommended_mode", "B"),
    ("active_mode", "B"), ("grade", "B"), ("reason", "B"), ("faults", "I"), ("events", "B"),
    ("override", "B"), ("reserved", "B"), ("force_cmd_n", "i"), ("road_est_um", "i"),
    ("dtd_est_um", "i"), ("gq_est_log_c", "i"), ("ba_rms_mmps2", "i"), ("dtd_rms_um", "i"),
    ("reserved", "i"))
_HASHED = struct.Struct("<" + "".join(code for _, code in HASHED))
# the ECU's per-tick trace columns (int64 rows of EcuNode.rows)
ECU_TRACE = ("road_est_um", "dtd_est_um", "force_cmd_n", "grade", "active_mode",
             "recommended_mode", "faults", "enable", "reason")


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


def true_grade_index(grade: str) -> int:
    return min(3, GRADES.index(grade))


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


class PlantNode:
    """The corner on the road: owns simulated time. Steps once per command (lockstep) or per
    clock tick (realtime). A command older than ``cmd_timeout_ticks`` is not applied: the
    bridge is opened and the corner falls back to passive behaviour."""

    name = "PLANT"

    def __init__(self, cfg: VehicleConfig, route: Route, seed: int, codec: Codec, *,
                 noise_step: Optional[tuple[float, float]] = None, cmd_timeout_ticks: int = 3,
                 inject=None, key: Optional[bytes] = None):
        self.cfg, self.route, self.seed, self.codec = cfg, route, seed, codec
        self.dt = dt = cfg.sim.plant_dt_s
        self.timeline = drive_timeline(route, dt)
        self.zf = road_at_ticks(generate_profile(route, seed), self.timeline)
        self.n = len(self.timeline)
        self.true_grade = np.array([true_grade_index(s.grade)
                                    for s in route.segments])[self.timeline.segment]
        self.sensors = SensorSuite(cfg.sensors, np.random.default_rng([seed, 0x5E45]))
        self.supply = SupplySensor(cfg.sensors.supply_voltage,
                                   np.random.default_rng([seed, 0x5E46]))
        self.active = QuarterCarPlant(cfg, actuator=True, ledger=True)
        self.twin = QuarterCarPlant(cfg, actuator=False)
        self.active.reset(self.zf[0])
        self.twin.reset(self.zf[0])
        self.twin_until = 0                 # the twin has been run up to this tick
        self.noise_step = noise_step
        self.cmd_timeout_ticks = cmd_timeout_ticks
        self.inject = inject                # hil.faults.injector.Injector (fault campaign) or None
        self.tx = Tx(codec)
        self.pack_sensors = codec.packer("PLANT_SENSORS", (   # in SensorReading's order
            "BODY_ACCEL_RAW", "WHEEL_ACCEL_RAW", "SUSP_DEFL_RAW", "MOTOR_CURRENT_RAW"))
        self.unpack_cmd = codec.unpacker("ACTUATOR_CMD", ("DUTY", "REGEN", "ENABLE",
                                                          "SENSOR_SEQ"))
        self.p_speed = period_ticks(codec, "VEHICLE_SPEED", dt)
        self.p_supply = period_ticks(codec, "PLANT_SUPPLY", dt)
        self.p_truth = period_ticks(codec, "SIM_TRUTH", dt)
        self.p_energy = period_ticks(codec, "ENERGY_STATUS", dt)
        self.cmd_rx = safety.RxState()
        self.cmd_rx_wire = safety.RxState()     # (fault campaign: every command on the wire)
        # SecOC (key None: the unsecured path, for tests of the receive path only)
        self.cmd_auth = secoc.receiver(codec, key, "ACTUATOR_CMD")
        self.cmd_auth_wire = copy.deepcopy(self.cmd_auth)
        self.auth_failures = 0              # ACTUATOR_CMD frames with a bad MAC or freshness
        self.auth_failures_booked = 0       # ... of them in the per-tick record so far
        # the frames on_frame does nothing with (a bus harness may skip them)
        self.ignore = frozenset(ID.values()) - {ID["ACTUATOR_CMD"]}
        self.k = 0
        self.cmd = (0, False, False)        # duty Q15, regen, enable
        self.cmd_tick = -1                  # tick of the last valid command
        self.cmd_fresh = False              # this tick's valid command arrived (lockstep)
        self.cmd_seq = -1                   # SENSOR_SEQ of the last valid command
        self.bad_cmd_frames = 0             # invalid ACTUATOR_CMD frames (not applied)
        self.stale_cmd_frames = 0           # valid, but not answering the tick's sensor frame
        self.missed_cmds = 0                # steps without a fresh command
        self.fallback_ticks = 0             # steps in the passive fallback
        # per tick: the active corner (plant.OBS, written by one compiled call), then the
        # command applied and whether the passive fallback acted
        self.obs = np.zeros((self.n, len(OBS) + 3))
        self.arrays = {k: np.zeros(self.n) for k in ("p_ba", "p_sws", "p_dtd", "p_vrel")}

    @property
    def done(self) -> bool:
        return self.k >= self.n

    def emit(self) -> list[Frame]:
        """Sample the sensors and return the frames of tick k (PLANT_SENSORS last)."""
        k, a = self.k, self.active
        if self.inject is not None:
            self.inject.before_emit(self)
        if self.noise_step is not None and k * self.dt >= self.noise_step[0]:
            self.sensors.noise_gain[:] = self.noise_step[1]
        r = self.sensors.sample(*a.sensed(), self.timeline.speed_mps.item(k))
        out = []
        if k % self.p_speed == 0:
            out.append(self.tx.frame("VEHICLE_SPEED", {"SPEED": r.speed}))
        if k % self.p_supply == 0:
            out.append(self.tx.frame("PLANT_SUPPLY", {
                "SUPPLY_VOLTAGE_RAW": self.supply.sample(a.bus_voltage_v)}))
        if k % self.p_truth == 0:
            out.append(self.tx.frame_phys("SIM_TRUTH", {
                "TRUE_ROAD": self.zf[k], "TRUE_DTD": a.x[3] - a.zf, "TRUE_SWS": a.x[2] - a.x[3],
                "TRUE_GRADE": int(self.true_grade[k]),
                "SEGMENT": int(self.timeline.segment[k])}))
        if k % self.p_energy == 0:
            out.append(self.tx.frame_phys("ENERGY_STATUS", {
                "STORED_ENERGY": a.stored_j, "SUPPLY_ENERGY": a.supply_drawn_j}))
        out.append(self.tx.frame_packed("PLANT_SENSORS", self.pack_sensors, r[:4]))
        if self.inject is not None:
            out = self.inject.after_emit(self, out)
        return out

    def on_frame(self, fid: int, data: bytes) -> list[Frame]:
        """Only a valid ACTUATOR_CMD (DLC, CHECKSUM, COUNTER, range) is applied, and only one
        that answers this tick's sensor frame (SENSOR_SEQ) ends the tick in lockstep; the rest
        are counted (``bad_cmd_frames``, ``stale_cmd_frames``) and never stepped on."""
        if fid == ID["ACTUATOR_CMD"]:
            if self.inject is not None:
                # the campaign's forged and replayed commands: received as any frame is
                for extra in self.inject.rx_extra(self, data):
                    self._receive_cmd(extra)
            self._receive_cmd(data)
        return []

    def _receive_cmd(self, data: bytes) -> None:
        on_wire = False
        if self.inject is not None:
            # the fault campaign loses commands in the plant's receiver after the ECU sent
            # them: the ECU's tick is over all the same (lockstep), as a receiver that sees
            # every frame on the wire judges it (the plant's own receiver rejects the first
            # command after a loss: its COUNTER jumped)
            w = self._checked(data, self.cmd_rx_wire, self.cmd_auth_wire)
            on_wire = w is not None and w is not _FORGED and self._answers(w[3])
            if self.inject.drop_rx(self, ID["ACTUATOR_CMD"]):
                self.cmd_fresh |= on_wire
                return
        v = self._checked(data, self.cmd_rx, self.cmd_auth)
        if v is _FORGED:
            self.auth_failures += 1
            return
        if v is None:
            self.bad_cmd_frames += 1
            self.cmd_fresh |= on_wire
            return
        duty, regen, enable, self.cmd_seq = v
        self.cmd = (duty, bool(regen), bool(enable))
        self.cmd_tick = self.k
        if self._answers(self.cmd_seq):
            self.cmd_fresh = True
        else:
            self.stale_cmd_frames += 1

    def _checked(self, data: bytes, rx: safety.RxState, auth):
        """The command's values if it is valid; ``_FORGED`` for a frame whose DLC and
        CHECKSUM hold but whose SecOC MAC or freshness fails (the COUNTER state untouched);
        None for an invalid frame (DLC, CHECKSUM, COUNTER, range: the unpacker's checks)."""
        if auth is not None and auth.forged(data):
            return _FORGED
        return self.unpack_cmd(data, rx, self.k)[0]

    def _answers(self, seq: int) -> bool:
        return seq == self.sensor_seq()

    # -- what a fault family may use (hil.faults): the node's public face ----------------------

    def sensor_seq(self) -> int:
        """The SENSOR_SEQ a command answering the last PLANT_SENSORS frame carries."""
        return (self.tx.counters.get("PLANT_SENSORS", 0) - 1) & 0x3

    def expected_cmd_counter(self) -> int:
        """The COUNTER the plant's command receiver expects next."""
        return (self.cmd_rx.last_counter + 1) & 0xF

    def encode(self, name: str, raw: dict) -> Frame:
        """A frame of this node's with raw values (its COUNTER advanced, counted as sent)."""
        return self.tx.frame(name, raw)

    def shift_counter(self, name: str, step: int) -> None:
        """Move the COUNTER of ``name``'s next frame by ``step``."""
        self.tx.counters[name] = (self.tx.counters.get(name, 0) + step) & 0xF

    def withdraw(self, fids: Iterable[int]) -> None:
        """These frames, built this tick, never reach the bus: not counted as sent."""
        for fid in fids:
            self.tx.sent[NAME_OF[fid]] -= 1

    def count_sent(self, label: str) -> None:
        """A frame put on the bus outside the DBC's messages (``label``: its ID)."""
        self.tx.sent[label] += 1

    @property
    def nominal_supply_v(self) -> float:
        return self.cfg.actuator.bus_voltage_v

    def set_supply_voltage(self, volts: float) -> None:
        self.active.set_bus_voltage(volts)

    def ready(self) -> bool:
        """Lockstep: the ECU's valid command answering this tick's sensor frame is in."""
        return self.cmd_fresh

    def answered(self) -> bool:
        """The last valid command answers this tick's sensor frame (its SENSOR_SEQ is the
        COUNTER, modulo 4, of the PLANT_SENSORS frame last sent)."""
        return self._answers(self.cmd_seq)

    def step(self) -> None:
        k, a, t = self.k, self.active, self.twin
        if not self.cmd_fresh:
            self.missed_cmds += 1
        duty, regen, enable = self.cmd
        fallback = self.cmd_tick < 0 or k - self.cmd_tick > self.cmd_timeout_ticks
        if fallback:
            duty, regen, enable = 0, False, False
            self.fallback_ticks += 1
        if self.inject is not None:     # (the fault campaign: the bridge, winding, supply)
            duty, regen, enable = self.inject.hardware(self, duty, regen, enable)
        a.step(self.zf[k + 1], duty / 32768.0, regen, enable)
        r = self.arrays
        if k >= self.twin_until:            # the passive twin only sees the road: run ahead
            end = min(self.n, k + TWIN_CHUNK)
            tw = t.run_passive(self.zf[k + 1:end + 1])
            for name in ("ba", "sws", "dtd", "vrel"):
                r["p_" + name][k:end] = tw[name]
            self.twin_until = end
        a.observe_into(self.obs, k)
        self.obs[k, _DUTY] = duty / 32768.0 if enable else 0.0
        self.obs[k, _FALLBACK] = fallback
        self.obs[k, _REJECTED] = self.auth_failures - self.auth_failures_booked
        self.auth_failures_booked = self.auth_failures
        self.k += 1
        self.cmd_fresh = False

    def summary(self) -> dict:
        out = {"node": "plant", "ticks": self.k, "frames_sent": dict(self.tx.sent),
               "energy": self.active.ledger.as_dict(), "bad_cmd_frames": self.bad_cmd_frames,
               "stale_cmd_frames": self.stale_cmd_frames, "auth_failures": self.auth_failures,
               "missed_cmds": self.missed_cmds, "fallback_ticks": self.fallback_ticks}
        if self.inject is not None:
            out["injected"] = self.inject.applied
        return out

    def trace(self) -> dict:
        k = self.k
        col = {**{name: i for i, name in enumerate(OBS)}, "duty": _DUTY, "fallback": _FALLBACK,
               "rejected": _REJECTED}
        out = {name: (self.arrays[name][:k] if name in self.arrays
                      else self.obs[:k, col[name]].copy()) for name in TRACE}
        out.update(zf=self.zf[1:k + 1], segment=self.timeline.segment[:k],
                   true_grade=self.true_grade[:k], speed=self.timeline.speed_mps[:k])
        return out


MISSING = object()   # a tick without a sensor frame (SIM_TICK: the ECU's timer ran alone)
_FORGED = object()   # a secured frame whose MAC or freshness failed


class EcuNode:
    """The firmware behind its CAN receive and transmit path, compiled
    (``hil.kernels.ecunode``: the receive table and the tick with its frames, the same
    functions the compiled SIL loop runs). Frame validity is ``firmware.safety``: an invalid
    PLANT_SENSORS frame, or a tick without one (SIM_TICK), feeds no counts (the ADC marks the
    channels faulty, the ECU goes fail-safe the same tick), VEHICLE_SPEED times out after 3
    periods and is rate-supervised (a copy sooner than half its period is not used), an
    invalid DRIVER_REQUEST is ignored; every frame fault is reported in the fault word.
    ECU_STATUS carries the OR of the fault words since the last ECU_STATUS, so a one-tick
    fault reaches the driver too. Without a ``key`` the node neither signs nor verifies
    (the unsecured path, for tests of the receive path only)."""

    name = "ECU"

    def __init__(self, params: fp.EcuParams, codec: Codec, *, lockstep: bool = True,
                 fixed_point: bool = False, record: bool = False, key: Optional[bytes] = None):
        self.params, self.codec, self.lockstep = params, codec, lockstep
        dt = params.dt_s
        # the compiled ECU (firmware), on the fixed-point path with its tables
        self.state = Ecu(params, build_tables(params) if fixed_point else None, record)
        self.M, self.F, self.fault_bits = codec.bus_tables()
        # the node's state (hil.kernels.ecunode.ECU_NODE) and its receivers: the firmware's
        # table (safety.RX_CHECKS) on the DBC's layout, in hil.kernels.bus' R_* rows
        self.E = kf.table(ken.ECU_NODE, 1)
        e = view(self.E)
        e.speed_raw = e.supply_new = -1
        e.seq = 3                           # COUNTER mod 4 of the sensor frame being answered
        e.last_rec[:] = -1
        e.p_status = period_ticks(codec, "ECU_STATUS", dt)
        e.p_rec = period_ticks(codec, "MODE_RECOMMEND", dt)
        e.lockstep, e.secured = lockstep, key is not None
        self.rx_specs = {ID[c.message]: rx_spec(codec, c, dt) for c in safety.RX_CHECKS}
        self.RX = kf.rx_table(len(_RX_ROWS))
        self._mi = {}                       # frame ID -> message index of the receive table
        for name, (row, mi) in _RX_ROWS.items():
            kf.supervise(self.RX[row], self.rx_specs[ID[name]])
            self._mi[ID[name]] = mi
        # SecOC: the command signed, the driver's request verified (libcrypto's CMAC)
        self.SEC = kf.table(ks.SEC, 4)
        for row, name in ((kb.S_CMD_TX, "ACTUATOR_CMD"), (kb.S_REQ_RX, "DRIVER_REQUEST")):
            lay = secoc.layout(codec, name)
            self.SEC[row]["fv_byte"], self.SEC[row]["mac_byte"] = lay.fv_byte, lay.mac_byte
        self.mac = Cmac(key) if key is not None else None
        self.key_sha = hashlib.sha256(key).hexdigest() if key is not None else None
        self.crypto = (self.mac.ctx if self.mac else 0, np.zeros(32, np.uint8),
                       self.mac.tag16 if self.mac else np.zeros(16, np.uint8),
                       self.mac.length if self.mac else np.zeros(1, np.uint64))
        self.ff = np.zeros((kb.NMSG, 32), np.int64)        # frame faults per message, bit
        self.ff_first = np.zeros((kb.NMSG, 32), np.int64)
        self._faults_py: dict[str, list[int]] = {}         # (missing, unknown IDs): [stamp, n]
        self._buf = np.zeros(8, np.uint8)
        self._out_mi, self._out = np.zeros(4, np.int64), np.zeros((4, 8), np.uint8)
        self._frame_of = [(ID[name], self.M[i]["dlc"]) for i, name in enumerate(kb.MESSAGES)]
        self._hrow = np.zeros(ken.ROW_BYTES, np.uint8)
        self._trow = np.zeros(len(ECU_TRACE), np.int64)
        # SIM_TICK (the simulated timer tick of a suppressed sensor frame) only in lockstep;
        # DIAG_REQUEST: a tester's UDS over ISO-TP (hil.apps.diag.UdsServer, made on first use)
        self.listen = set(self.rx_specs) | {ID["DIAG_REQUEST"]} | (
            {ID["SIM_TICK"]} if lockstep else set())
        self.uds = None
        self.diag_sent = 0                  # DIAG_RESPONSE frames sent
        # known frames of others (and SIM_TRUTH): on_frame does nothing with them
        self.ignore = frozenset(ID.values()) - self.listen
        self.pending: deque = deque()       # sensor samples not yet processed
        self.held_cmd: Optional[Frame] = None   # lockstep: ACTUATOR_CMD waiting for answers
        self.unrecorded = False             # the last tick, until record() books it
        self.resets = 0                     # ECU resets a tester asked for (UDS 0x11)
        self.sha = hashlib.sha256()
        self.rows = array("q")              # per tick: ECU_TRACE
        self.hashed: Optional[bytearray] = None   # (a bytearray: every tick's hashed row)

    # the node's state, read by name
    @property
    def k(self) -> int:
        return int(self.E[0]["k"])

    @property
    def link_faults(self) -> int:
        """The frame faults of the tick being received (reported with its ECU tick)."""
        return int(self.E[0]["link_faults"])

    @property
    def req(self) -> tuple[int, int, int]:
        """The driver's latest valid request: (kind, mode, id)."""
        e = self.E[0]
        return int(e["req_kind"]), int(e["req_mode"]), int(e["req_id"])

    @property
    def awaiting(self) -> int:
        """MODE_RECOMMEND frames sent and not yet answered."""
        return int(self.E[0]["awaiting"])

    @property
    def rx(self) -> dict:
        """The receivers by frame ID (``firmware.safety.RxState``'s fields, read through)."""
        rows = self.RX.view(np.recarray)
        return {ID[name]: rows[row] for name, (row, _) in _RX_ROWS.items()}

    @property
    def frame_faults(self) -> Counter:
        """Frame faults seen, by ``MESSAGE:fault``, in the order first seen."""
        names = safety.FAULT_NAMES
        found = [(int(self.ff_first[i, b]), f"{kb.MESSAGES[i]}:{names.get(1 << int(b), b)}",
                  int(self.ff[i, b])) for i, b in zip(*np.nonzero(self.ff))]
        found += [(stamp, label, n) for label, (stamp, n) in self._faults_py.items()]
        return Counter({label: n for _, label, n in sorted(found)})

    def _note_py(self, faults: int, label: str) -> None:
        """A frame fault the receive table does not see (a missing frame, an unknown ID)."""
        e = self.E[0]
        e["link_faults"] |= faults
        entry = self._faults_py.get(label)
        if entry is None:
            entry = self._faults_py[label] = [int(e["ff_stamp"]), 0]
            e["ff_stamp"] += 1
        entry[1] += 1

    def on_frame(self, fid: int, data: bytes) -> list[Frame]:
        if fid in self.ignore:
            return []
        if fid == _SIM_TICK:
            self.pending.append(MISSING)
            return []
        if fid == _DIAG_REQUEST:
            return self._diag(data)
        mi = self._mi.get(fid)
        if mi is None:
            self._note_py(safety.FAULT_UNKNOWN_ID, f"0x{fid:X}")
            return []
        n = len(data)
        buf = self._buf
        buf[:] = 0
        buf[:min(n, 8)] = np.frombuffer(data[:8], np.uint8)
        got = ken.receive(self.E, self.M, self.F, self.RX, self.SEC, self.crypto, self.ff,
                          self.ff_first, mi, buf, n)
        if mi == kb.M_SENSORS:
            self.pending.append(tuple(self.E[0]["counts"].tolist()) if got == ken.RX_SAMPLE
                                else None)
        elif got == ken.RX_RELEASE and self.held_cmd is not None:
            cmd, self.held_cmd = self.held_cmd, None
            return [cmd]
        return []

    def ready(self) -> bool:
        return bool(self.pending) and self.held_cmd is None

    def _diag(self, data: bytes) -> list[Frame]:
        """A tester's frame: the ISO-TP answer (flow control, the UDS response). Between
        ticks; the control state is untouched but for a reset (0x11), carried out here after
        its response is queued: a new operation cycle, the DTC memory kept."""
        if self.uds is None:
            from hil.apps.diag import UdsServer

            self.uds = UdsServer(lambda req: uds.handle(self.state.diag, self.params, self.k,
                                                        req))
        frames = self.uds.on_frame(data)
        return self._diag_out(frames)

    def _diag_out(self, frames: list[Frame]) -> list[Frame]:
        self.diag_sent += len(frames)
        if self.state.diag.reset_requested:
            self.state.reset()
            self.resets += 1
        return frames

    def timer_tick(self) -> None:
        """Realtime pacing: the ECU's own timer fired without a sensor frame (bus silence)."""
        self.pending.append(MISSING)

    def tick(self) -> list[Frame]:
        self.record()
        s = self.pending.popleft()
        if s is MISSING:
            e = self.E[0]
            e["seq"] = (e["seq"] + 1) & 0x3
            self._note_py(safety.FAULT_TIMEOUT, "PLANT_SENSORS:missing")
            s = None
        st = self.state
        c = s or _NO_COUNTS
        n, awaiting = ken.tick(self.E, self.M, self.F, self.fault_bits, self.RX, self.SEC,
                               self.crypto, st.P, st.T, st.S, st.I, st.O, s is not None,
                               c[0], c[1], c[2], c[3], self._out_mi, self._out)
        if st.log is not None:
            st.log.append(st.fx_tick())
        frame_of, out = self._frame_of, self._out
        frames = []
        for i, mi in enumerate(self._out_mi[:n].tolist()):
            fid, dlc = frame_of[mi]
            frames.append((fid, out[i, :dlc].tobytes()))
        cmd = frames.pop(0)
        # the command first in realtime (the plant waits for it); held in lockstep while a
        # MODE_RECOMMEND awaits its answer, else last
        if not self.lockstep:
            frames.insert(0, cmd)
        elif awaiting:
            self.held_cmd = cmd
        else:
            frames.append(cmd)
        self.unrecorded = True
        if self.uds is not None and self.uds.busy:   # (a transfer's ISO-TP timers)
            frames += self._diag_out(self.uds.poll())
        return frames

    def record(self) -> None:
        """The tick's bookkeeping (trace hash, per-tick record), kept off the path from the
        sensor frame to the command: callers run it after sending the tick's frames; the next
        tick and ``summary``/``trace`` run it when they did not."""
        if not self.unrecorded:
            return
        self.unrecorded = False
        st = self.state
        ken.record(self.E, st.I, st.O, self._hrow, 0, self._trow)
        self.sha.update(self._hrow)
        if self.hashed is not None:
            self.hashed += self._hrow.tobytes()
        self.rows.frombytes(self._trow.tobytes())

    def frames_sent(self) -> dict[str, int]:
        out = {name: int(self.E[0]["sent"][kb.MESSAGES.index(name)])
               for name in ("ACTUATOR_CMD", "ECU_STATUS", "ECU_ESTIMATES", "MODE_RECOMMEND")}
        out = {name: n for name, n in out.items() if n}
        if self.diag_sent:
            out["DIAG_RESPONSE"] = self.diag_sent
        return out

    def summary(self) -> dict:
        self.record()
        return {"node": "ecu", "ticks": self.k, "frames_sent": self.frames_sent(),
                "trace_sha256": self.sha.hexdigest(),
                "akf_r_guard_hits": self.state.guard_hits,
                "frame_faults": dict(self.frame_faults),
                "arithmetic": self.state.arithmetic,
                "uds_requests": self.uds.requests if self.uds else 0,
                "isotp_errors": self.uds.errors if self.uds else 0, "ecu_resets": self.resets,
                "fx_gain_saturations": self.state.gain_saturations}

    def trace(self) -> dict:
        self.record()
        c = np.array(self.rows, dtype=np.int64).reshape(-1, len(ECU_TRACE)).T   # (a copy)
        return {"road_est": c[0] * 1e-6, "dtd_est": c[1] * 1e-6,
                "force_cmd": c[2].astype(float), "grade_est": c[3].astype(np.int16),
                "mode": c[4].astype(np.int8), "recommended": c[5].astype(np.int8),
                "faults": c[6].astype(np.int32), "enable": c[7].astype(bool),
                "reason": c[8].astype(np.int8)}


# the ECU's receive table: message -> (its receiver's row, its message index), hil.kernels.bus
_RX_ROWS = {"VEHICLE_SPEED": (kb.R_SPEED, kb.M_SPEED),
            "PLANT_SUPPLY": (kb.R_SUPPLY, kb.M_SUPPLY),
            "PLANT_SENSORS": (kb.R_SENSORS, kb.M_SENSORS),
            "DRIVER_REQUEST": (kb.R_REQ, kb.M_REQ)}
_NO_COUNTS = (-1, -1, -1, -1)
_SIM_TICK, _DIAG_REQUEST = ID["SIM_TICK"], ID["DIAG_REQUEST"]


REQ_KINDS = {"none": fp.REQ_NONE, "accept": fp.REQ_ACCEPT, "refuse": fp.REQ_REFUSE,
             "choose": fp.REQ_CHOOSE}
POLICIES = ("auto", "fixed", "refuse", "script", "interactive", "web")
QUEUED = ("interactive", "web")       # the policies that send what a person chose


class AppNode:
    """The driver-app emulator. Time is the ECU's: 10 ms per ECU_STATUS received. Answers every
    MODE_RECOMMEND with one DRIVER_REQUEST (a new request, or the heartbeat repeating the last).

    Policies: ``auto`` accepts a recommendation once it has been shown unchanged for the
    reaction delay; ``fixed`` chooses ``mode`` at start, then refuses every recommendation;
    ``refuse`` refuses every recommendation; ``script`` sends timed choices
    [(t_s, kind, mode or None), ...] (``accept`` with no mode accepts what is recommended then);
    ``interactive`` and ``web`` send what :meth:`push` queued (keys in a terminal, clicks
    on the page of ``hil.apps.webapp``)."""

    name = "APP"

    def __init__(self, codec: Codec, policy: str = "auto", *, mode: int = fp.MODE_PASSIVE,
                 reaction_ticks: int = 1000, script: Optional[Iterable] = None,
                 dt: float = 0.001, inject=None, key: Optional[bytes] = None):
        if policy not in POLICIES:
            raise ValueError(f"unknown driver policy {policy!r} (one of {', '.join(POLICIES)})")
        self.codec, self.policy, self.mode, self.dt = codec, policy, mode, dt
        self.reaction_ticks = reaction_ticks
        self.script = deque(sorted(script or [], key=lambda e: e[0]))
        self.tx = Tx(codec)
        # the frames on_frame does nothing with (a bus harness may skip them)
        self.ignore = frozenset(ID.values()) - {ID[n] for n in (
            "ECU_STATUS", "VEHICLE_SPEED", "MODE_RECOMMEND", "ENERGY_STATUS")}
        self.p_status = period_ticks(codec, "ECU_STATUS", dt)
        self.n_status = 0
        self.t = 0                           # ticks of simulated time (from ECU_STATUS)
        self.kind, self.req_mode, self.req_id = fp.REQ_NONE, 0, 0
        self._shown, self._shown_since, self._answered = -1, 0, -1
        self._chosen = False
        self.queued: deque = deque()         # interactive choices (kind, mode)
        self.view: dict = {}                 # latest decoded status for a display
        self.log: list[tuple[float, str, int]] = []   # (t_s, kind, mode) of requests sent
        self.on_request: Optional[Callable[[float, str, int], None]] = None
        # what the driver is told: (tick, FAULTS, REASON) of ECU_STATUS, on each change
        self.faults_seen: list[tuple[int, int, int]] = []
        self.on_faults: Optional[Callable[[float, int, int], None]] = None
        # what the ECU recommends, told on each change: (t_s, recommended, active)
        self.on_recommend: Optional[Callable[[float, int, int], None]] = None
        self._told = None
        self.inject = inject                 # hil.faults.injector.Injector (fault campaign) or None
        self.req_sec = secoc.sender(codec, key, "DRIVER_REQUEST")

    def push(self, kind: str, mode: Optional[int] = None) -> None:
        self.queued.append((kind, mode))

    def script_due(self) -> bool:
        """The script's next entry is due (it goes with the next MODE_RECOMMEND)."""
        return bool(self.script) and self.script[0][0] <= self.t * self.dt + 1e-9

    def request(self, kind: int, mode: int) -> None:
        """Send a DRIVER_REQUEST of ``kind`` for ``mode`` with the next answer."""
        self.kind, self.req_mode = kind, mode
        self.req_id = (self.req_id + 1) & 0xF
        name = next(k for k, v in REQ_KINDS.items() if v == kind)
        self.log.append((self.t * self.dt, name, mode))
        if self.on_request is not None:
            self.on_request(self.t * self.dt, name, mode)

    def _decide(self, rec: int, active: int, reason: int = REASON_NONE) -> None:
        t = self.t
        if self.policy == "fixed" and not self._chosen:
            self._chosen = True
            self.request(fp.REQ_CHOOSE, self.mode)
            return
        if self.policy == "script":
            while self.script_due():
                _, kind, mode = self.script.popleft()
                self.request(REQ_KINDS[kind], rec if mode is None else mode)
            return
        if self.policy in QUEUED:
            if self.queued:
                kind, mode = self.queued.popleft()
                self.request(REQ_KINDS[kind], rec if mode is None else mode)
            return
        if rec != self._shown:
            self._shown, self._shown_since = rec, t
        if reason != REASON_NONE:
            # the ECU overrides the driver's mode (road holding, a fault): the active mode is
            # not the driver's, so a recommendation that differs from it asks nothing of the
            # driver (accepting or refusing it again would be a second request in a few ticks)
            return
        if (rec != active and rec != self._answered
                and t - self._shown_since >= self.reaction_ticks):
            self._answered = rec
            self.request(fp.REQ_ACCEPT if self.policy == "auto" else fp.REQ_REFUSE, rec)
        if rec == active:
            self._answered = -1

    def on_frame(self, fid: int, data: bytes) -> list[Frame]:
        if fid == ID["ECU_STATUS"]:
            d = self.codec.decode(fid, data)
            self.n_status += 1
            self.t = (self.n_status - 1) * self.p_status
            if d.ok:
                self.view.update(d.signals)
                seen = (fault_word(d.signals), int(d.signals["REASON"]))
                if seen != (self.faults_seen[-1][1:] if self.faults_seen else (0, 0)):
                    self.faults_seen.append((self.t, *seen))
                    if self.on_faults is not None:
                        self.on_faults(self.t * self.dt, *seen)
        elif fid in (ID["VEHICLE_SPEED"], ID["ENERGY_STATUS"]):
            d = self.codec.decode(fid, data)
            if d.ok:
                self.view.update(d.signals)
        elif fid == ID["MODE_RECOMMEND"]:
            d = self.codec.decode(fid, data, scaling=False)
            if d.ok:
                s = d.signals
                self.view.update({f"REC_{k}": v for k, v in s.items()})
                rec = (int(s["RECOMMENDED_MODE"]), int(s["ACTIVE_MODE"]))
                if rec != self._told and self.on_recommend is not None:
                    self._told = rec
                    self.on_recommend(self.t * self.dt, *rec)
                self._decide(*rec, int(s["REASON"]))
                if self.inject is not None:
                    self.inject.before_answer(self)
            fid, data = self.tx.frame("DRIVER_REQUEST", {
                "REQ_KIND": self.kind, "REQ_MODE": self.req_mode, "REQ_ID": self.req_id})
            return [(fid, self.req_sec.protect(data) if self.req_sec is not None else data)]
        return []

    def summary(self) -> dict:
        kinds = Counter(k for _, k, _ in self.log)
        out = {"node": "app", "policy": self.policy, "frames_sent": dict(self.tx.sent),
               "requests": dict(kinds), "log": [list(e) for e in self.log],
               "faults_seen": [list(e) for e in self.faults_seen]}
        if self.inject is not None:
            out["injected"] = self.inject.applied
        return out


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


def run_in_process(plant: PlantNode, ecu_node: EcuNode, app: AppNode,
                   on_frame: Optional[Callable[[int, bytes], None]] = None,
                   progress: Optional[Callable[[int, int], None]] = None,
                   until: Optional[int] = None) -> dict[str, int]:
    """The lockstep protocol with the three nodes in this process: a FIFO stands in for the
    bus (every frame goes to every other node, in the order sent), up to tick ``until`` (the
    route's end by default). Returns the frames that crossed the FIFO, per message name."""
    nodes = (plant, ecu_node, app)
    queue: deque = deque()
    routes: dict = {}     # (sender, frame ID) -> the nodes that do not ignore it
    seen: Counter = Counter()

    def send(sender, frames):
        queue.extend((sender, f) for f in frames)
        while queue:
            src, (fid, data) = queue.popleft()
            seen[fid] += 1
            if on_frame is not None:
                on_frame(fid, data)
            dests = routes.get((src, fid))
            if dests is None:
                dests = routes[src, fid] = tuple(
                    n for n in nodes if n is not src and fid not in getattr(n, "ignore", ()))
            for node in dests:
                replies = node.on_frame(fid, data)
                if replies:
                    queue.extend((node, r) for r in replies)

    report_every = max(1, plant.n // 200)
    end = plant.n if until is None else min(plant.n, until)
    while plant.k < end:
        send(plant, plant.emit())
        while ecu_node.ready():
            send(ecu_node, ecu_node.tick())
            ecu_node.record()
        if not plant.ready():
            raise RuntimeError(f"lockstep broken at tick {plant.k}")
        plant.step()
        if progress is not None and (plant.k % report_every == 0 or plant.done):
            progress(plant.k, plant.n)
    return {message_name(fid): n for fid, n in seen.items()}


def warm_up(node, ticks: int = 30) -> None:
    """Run the node's code paths a few times on a throwaway copy before the real run: numba
    loads a kernel from its cache (or compiles it) on its first call, 0.2 s for the first one
    in a process, and Python's first pass through a path is slower; in realtime pacing both
    would be missed deadlines at the start. The plant copy steps with an enabled command; the
    ECU copy gets valid sensor and speed frames and one tick without a sensor frame (its
    compiled tick, ``firmware``, is one function: the first call loads all of it). The
    node itself is untouched (the same bytes on the bus afterwards)."""
    shared = {id(node.codec): node.codec}
    if hasattr(node, "params"):             # the calibration: the same arrays (and layouts)
        shared[id(node.params)] = node.params
    for rec in (getattr(getattr(node, "state", None), name, None) for name in ("P", "T")):
        if rec is not None:                 # (its records: read-only, a copy is not)
            shared[id(rec)] = rec
    if getattr(node, "inject", None) is not None:
        shared[id(node.inject)] = node.inject
    if getattr(node, "mac", None) is not None:     # (a CMAC context does not copy; its
        shared[id(node.mac)] = node.mac            # callers' freshness is in their tables)
    if hasattr(node, "sha"):
        shared[id(node.sha)] = hashlib.sha256()   # (a hash object does not copy)
    w = copy.deepcopy(node, shared)
    if isinstance(w, PlantNode):
        w.inject = None
        for k in range(min(ticks, w.n)):
            w.emit()
            w.cmd, w.cmd_tick, w.cmd_fresh = (1000 * (k % 3 - 1), k % 2 == 0, True), w.k, True
            w.step()
    elif isinstance(w, EcuNode):
        tx = Tx(w.codec)
        for k in range(ticks):
            if k % 10 == 0:
                w.on_frame(*tx.frame_phys("VEHICLE_SPEED", {"SPEED": 20.0}))
            w.on_frame(*tx.frame("PLANT_SENSORS", {
                "BODY_ACCEL_RAW": 2048 + k, "WHEEL_ACCEL_RAW": 2048 - k, "SUSP_DEFL_RAW": 2048,
                "MOTOR_CURRENT_RAW": 2048}))
            while w.ready():
                w.tick()
                w.record()
        w.pending.append(MISSING)
        w.tick()
        w.record()      # (the tick is one compiled function: every controller came with it)
