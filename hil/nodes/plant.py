"""The plant node: the corner on the road (road, quarter car, sensors, passive twin) behind
its CAN frames."""

from __future__ import annotations

import copy
from typing import Iterable, Optional

import numpy as np

from calib.vehicle import VehicleConfig
from firmware import safety
from hil.nodes.base import (_FORGED, ID, NAME_OF, Frame, Tx, period_ticks,
                             true_grade_index)
from hil.sim.drive import road_at_ticks
from hil.sim.plant import OBS, QuarterCarPlant
from hil.sim.road import Route, drive_timeline, generate_profile
from hil.sim.sensors import SensorSuite, SupplySensor
from hil.transport import secoc
from hil.transport.codec import Codec

TWIN_CHUNK = 250                        # passive-twin ticks computed per batch

# PlantNode.obs columns after plant.OBS: the duty applied, the passive fallback, and the
# commands rejected by SecOC in that tick
_DUTY, _FALLBACK, _REJECTED = len(OBS), len(OBS) + 1, len(OBS) + 2
TRACE = ("ba", "sws", "dtd", "force", "p_ba", "p_sws", "p_dtd", "p_vrel", "stored", "drawn",
         "duty", "fallback", "rejected")       # the plant's trace columns


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
        r = self.sensors.sample(*a.sensed(), self.timeline.speed_mps.item(k), k)
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
