"""The ECU node: the firmware behind its CAN receive and transmit path, compiled."""

from __future__ import annotations

import struct
import hashlib
from array import array
from collections import Counter, deque
from typing import Optional

import numpy as np

from calib.fx_tables import build_tables
from firmware import adc, safety
from firmware import params as fp
from firmware.diag import dtc, uds
from firmware.ecu import Ecu
from firmware.layout import view
from hil.kernels import bus as kb
from hil.kernels import ecunode as ken
from hil.kernels import frames as kf
from hil.kernels import secoc as ks
from hil.kernels.cmac import Cmac
from hil.nodes.base import MISSING, ID, Frame, period_ticks, rx_spec
from hil.transport import secoc
from hil.transport.codec import Codec

# What the trace hash takes per tick, in this order: the ECU's inputs, then its outputs, each
# packed little-endian with its struct code. The "reserved" field is always 0 and "degraded"
# (firmware.diag.degrade, a reserved byte before) is 0 while no sensor is out: every trace hash
# recorded before (tests/golden, earlier reports) stays valid.
HASHED = (
    ("tick", "q"), ("body_accel", "i"), ("wheel_accel", "i"), ("susp_defl", "i"),
    ("motor_current", "i"), ("speed", "i"), ("supply", "i"),   # counts as received, -1: none
    ("req_kind", "i"), ("req_mode", "i"), ("req_counter", "i"), ("link_faults", "I"),
    ("duty_q15", "i"), ("regen", "B"), ("enable", "B"), ("recommended_mode", "B"),
    ("active_mode", "B"), ("grade", "B"), ("reason", "B"), ("faults", "I"), ("events", "B"),
    ("override", "B"), ("degraded", "B"), ("force_cmd_n", "i"), ("road_est_um", "i"),
    ("dtd_est_um", "i"), ("gq_est_log_c", "i"), ("ba_rms_mmps2", "i"), ("dtd_rms_um", "i"),
    ("reserved", "i"))
HASHED_ROW = struct.Struct("<" + "".join(code for _, code in HASHED))
# the ECU's per-tick trace columns (int64 rows of EcuNode.rows)
ECU_TRACE = ("road_est_um", "dtd_est_um", "force_cmd_n", "grade", "active_mode",
             "recommended_mode", "faults", "enable", "reason", "degraded")

# the ECU's receive table: message -> (its receiver's row, its message index), hil.kernels.bus
_RX_ROWS = {"VEHICLE_SPEED": (kb.R_SPEED, kb.M_SPEED),
            "PLANT_SUPPLY": (kb.R_SUPPLY, kb.M_SUPPLY),
            "PLANT_SENSORS": (kb.R_SENSORS, kb.M_SENSORS),
            "DRIVER_REQUEST": (kb.R_REQ, kb.M_REQ)}
_NO_COUNTS = (adc.NO_SAMPLE,) * 4
_SIM_TICK, _DIAG_REQUEST, _XCP_CMD = ID["SIM_TICK"], ID["DIAG_REQUEST"], ID["XCP_CMD"]


class EcuNode:
    """The firmware behind its CAN receive and transmit path, compiled
    (``hil.kernels.ecunode``: the receive table and the tick with its frames, the same
    functions the compiled SIL loop runs). Frame validity is ``firmware.safety``: an invalid
    PLANT_SENSORS frame, or a tick without one (SIM_TICK), feeds no counts (no sample: the
    channels hold their values, the ECU goes fail-safe the same tick, and the frame's own
    fault names it, not the sensors' circuits), VEHICLE_SPEED times out after 3
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
        # DIAG_REQUEST: a tester's UDS over ISO-TP (hil.apps.diag.UdsServer, made on first use);
        # XCP_CMD: a calibration tool's XCP (hil.xcp.port.XcpPort, made on first use; it
        # needs the run's key for its seed and key)
        self.listen = set(self.rx_specs) | {ID["DIAG_REQUEST"]} | (
            {ID["SIM_TICK"]} if lockstep else set()) | ({_XCP_CMD} if key is not None else set())
        self.uds = None
        self.xcp = None
        self._key = key
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
        if fid == _XCP_CMD:
            if self.xcp is None:
                from hil.xcp.port import XcpPort

                self.xcp = XcpPort(self.state, self.codec, self._key)
            return self.xcp.on_frame(data)
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
        if self.xcp is not None:            # (calibration: between two ticks)
            self.xcp.before_tick()
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
        if self.xcp is not None:            # (DAQ: the tick's end is its events' boundary)
            frames += self.xcp.after_tick()
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
        if self.xcp is not None and self.xcp.sent:
            out["XCP_RES"] = self.xcp.sent
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
                "fx_gain_saturations": self.state.gain_saturations,
                "dtcs_confirmed": self.confirmed_dtcs(),
                **({"xcp": self.xcp.summary()} if self.xcp is not None else {})}

    def confirmed_dtcs(self) -> list[str]:
        """The DTCs whose confirmedDTC bit is set in the ECU's memory now, by name."""
        status = self.state.S[0]["dtc"]["status"]
        return [d.name for i, d in enumerate(dtc.DTCS) if status[i] & dtc.CDTC]

    def trace(self) -> dict:
        self.record()
        c = np.array(self.rows, dtype=np.int64).reshape(-1, len(ECU_TRACE)).T   # (a copy)
        return {"road_est": c[0] * 1e-6, "dtd_est": c[1] * 1e-6,
                "force_cmd": c[2].astype(float), "grade_est": c[3].astype(np.int16),
                "mode": c[4].astype(np.int8), "recommended": c[5].astype(np.int8),
                "faults": c[6].astype(np.int32), "enable": c[7].astype(bool),
                "reason": c[8].astype(np.int8), "degraded": c[9].astype(np.int8)}
