"""Software-in-the-loop: the whole ECU (ADC, AKF, modes, controllers, actuator stage) against
the plant in one process, with a passive twin on the same road.

Per tick k: the plant's sensors are sampled (noise, ADC) -> the driver emulator answers the
ECU's last recommendation -> ``firmware.ecu.step`` -> the plant steps with the PWM duty, regen
switch and bridge enable -> the passive twin steps. Every input and output of the ECU is hashed
(``trace_sha256``), so a seed and a configuration pin the run to the byte.
"""

from __future__ import annotations

import dataclasses
import hashlib
import struct
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from firmware import ecu
from firmware import params as fp
from hil.config import VehicleConfig
from hil.drive import road_at_ticks
from hil.ecu_params import DesignOptions, build, with_controllers
from hil.metrics import rms
from hil.plant import QuarterCarPlant
from hil.road import GRADES, Route, drive_timeline, generate_profile
from hil.sensors import SensorSuite

MODES = {"passive": fp.MODE_PASSIVE, "regen": fp.MODE_ENERGY, "comfort": fp.MODE_COMFORT,
         "safety": fp.MODE_SAFETY, "comprehensive": fp.MODE_COMPREHENSIVE}
CONTROLLERS = {"pid": fp.CTRL_PID, "bppid": fp.CTRL_BPPID, "lqr": fp.CTRL_LQR,
               "galqr": fp.CTRL_GALQR, "skyhook": fp.CTRL_SKYHOOK, "regen": fp.CTRL_REGEN}
SETTLE_S = 3.0
REACTION_S = 1.0

_IN = struct.Struct("<q5i3i")
_OUT = struct.Struct("<i2B4BIBBB7i")


class Driver:
    """The driver-app emulator. ``auto``: accept the ECU's recommendation once it has been
    shown unchanged for the reaction delay. ``fixed``: choose one mode at start, then refuse
    every recommendation. ``script``: timed choices [(t_s, kind, mode), ...]."""

    def __init__(self, policy: str, mode: int = fp.MODE_PASSIVE, reaction_ticks: int = 1000,
                 script: Optional[list] = None, dt: float = 0.001):
        self.policy = policy
        self.mode = mode
        self.reaction_ticks = reaction_ticks
        self.script = sorted(script or [])
        self.dt = dt
        self.kind, self.req_mode, self.counter = fp.REQ_NONE, 0, 0
        self._shown, self._shown_since, self._answered = -1, 0, -1

    def _send(self, kind: int, mode: int) -> None:
        self.kind, self.req_mode = kind, mode
        self.counter = (self.counter + 1) & 0xF

    def request(self, tick: int, last: Optional[ecu.Outputs]) -> tuple[int, int, int]:
        if self.policy == "fixed" and tick == 0:
            self._send(fp.REQ_CHOOSE, self.mode)
        elif self.policy == "script":
            while self.script and self.script[0][0] <= tick * self.dt:
                _, kind, mode = self.script.pop(0)
                self._send(kind, mode)
        elif last is not None and self.policy in ("auto", "fixed", "refuse"):
            rec = last.recommended_mode
            if rec != self._shown:
                self._shown, self._shown_since = rec, tick
            if (rec != last.active_mode and rec != self._answered
                    and tick - self._shown_since >= self.reaction_ticks):
                self._answered = rec
                self._send(fp.REQ_ACCEPT if self.policy == "auto" else fp.REQ_REFUSE, rec)
            if rec == last.active_mode:
                self._answered = -1
        return self.kind, self.req_mode, self.counter


@dataclass
class SilTrace:
    dt_s: float
    segment: np.ndarray
    true_grade: np.ndarray
    arrays: dict = field(default_factory=dict)


def true_grade_index(grade: str) -> int:
    return min(3, GRADES.index(grade))


def run(cfg: VehicleConfig, route: Route, mode: str, seed: int, *,
        controller: Optional[str] = None, opts: Optional[DesignOptions] = None,
        gains_file=None, driver: Optional[Driver] = None,
        params: Optional[fp.EcuParams] = None, noise_step: Optional[tuple[float, float]] = None,
        progress: Optional[Callable[[int, int], None]] = None) -> tuple[dict, SilTrace]:
    """Run the SIL. Returns (report dict, per-tick trace)."""
    if mode not in MODES and mode != "auto":
        raise ValueError(f"unknown mode {mode!r}")
    dt = cfg.sim.plant_dt_s
    # in this harness the ECU ticks once per plant step
    opts = dataclasses.replace(opts, dt_s=dt) if opts else DesignOptions(dt_s=dt)
    p = params or build(cfg, opts, gains_file)
    if abs(p.dt_s - dt) > 1e-12:
        raise ValueError(f"ECU tick {p.dt_s} s differs from the plant step {dt} s")
    if controller is not None:
        target = fp.MODE_COMFORT if mode in ("auto", "passive") else MODES[mode]
        p = with_controllers(p, target, CONTROLLERS[controller])
    if driver is None:
        driver = (Driver("auto", reaction_ticks=int(round(REACTION_S / dt)), dt=dt)
                  if mode == "auto" else Driver("fixed", MODES[mode], dt=dt))
    timeline = drive_timeline(route, dt)
    zf = road_at_ticks(generate_profile(route, seed), timeline)
    n = len(timeline)
    sensors = SensorSuite(cfg.sensors, np.random.default_rng([seed, 0x5E45]))
    active = QuarterCarPlant(cfg, actuator=True, ledger=True)
    twin = QuarterCarPlant(cfg, actuator=False)
    active.reset(zf[0])
    twin.reset(zf[0])
    state = ecu.init(p)
    sha = hashlib.sha256()
    names = ("ba", "sws", "dtd", "force", "p_ba", "p_sws", "p_dtd", "p_vrel", "road_est", "dtd_est",
             "force_cmd")
    rec = {k: np.empty(n) for k in names}
    grade_est = np.empty(n, dtype=np.int16)
    mode_act = np.empty(n, dtype=np.int8)
    stored = np.empty(n)
    drawn = np.empty(n)
    last = None
    report_every = max(1, n // 200)
    for k in range(n):
        if noise_step is not None and k * dt >= noise_step[0]:
            sensors.noise_gain[:] = noise_step[1]
        ba, wa = active.accelerations()
        r = sensors.sample(ba, wa, active.susp_defl_m, active.current_a, timeline.speed_mps[k])
        kind, rmode, counter = driver.request(k, last)
        inp = ecu.Inputs(k, r.body_accel, r.wheel_accel, r.susp_defl, r.motor_current, r.speed,
                         kind, rmode, counter)
        state, out = ecu.step(state, inp)
        sha.update(_IN.pack(k, r.body_accel, r.wheel_accel, r.susp_defl, r.motor_current,
                            r.speed, kind, rmode, counter))
        sha.update(_OUT.pack(out.duty_q15, out.regen, out.enable, out.recommended_mode,
                             out.active_mode, out.grade, out.reason, out.faults, out.events,
                             out.override, 0, out.force_cmd_n, out.road_est_um, out.dtd_est_um,
                             out.gq_est_log_c, out.ba_rms_mmps2, out.dtd_rms_um, 0))
        last = out
        active.step(zf[k + 1], out.duty_q15 / 32768.0, out.regen, out.enable)
        twin.step(zf[k + 1])
        rec["ba"][k], _ = active.accelerations()
        rec["sws"][k] = active.x[2] - active.x[3]
        rec["dtd"][k] = active.x[3] - active.zf
        rec["force"][k] = active.actuator_force_n()
        rec["p_ba"][k], _ = twin.accelerations()
        rec["p_sws"][k] = twin.x[2] - twin.x[3]
        rec["p_dtd"][k] = twin.x[3] - twin.zf
        rec["p_vrel"][k] = twin.x[0] - twin.x[1]
        rec["road_est"][k] = out.road_est_um * 1e-6
        rec["dtd_est"][k] = out.dtd_est_um * 1e-6
        rec["force_cmd"][k] = out.force_cmd_n
        grade_est[k] = out.grade
        mode_act[k] = out.active_mode
        stored[k] = active.ledger.stored_j
        drawn[k] = active.ledger.supply_drawn_j
        if progress is not None and (k % report_every == 0 or k == n - 1):
            progress(k + 1, n)
    true_grade = np.array([true_grade_index(s.grade) for s in route.segments])[timeline.segment]
    trace = SilTrace(dt, timeline.segment, true_grade,
                     dict(rec, grade_est=grade_est, mode=mode_act, stored=stored, drawn=drawn,
                          zf=zf[1:]))
    report = _report(cfg, route, mode, controller, seed, trace, active, sha.hexdigest(), state)
    return report, trace


def _report(cfg, route, mode, controller, seed, trace, plant, digest, state) -> dict:
    dt = trace.dt_s
    a = trace.arrays
    settle = int(round(SETTLE_S / dt))
    segments = []
    acc_hits = acc_n = 0
    c_s = cfg.vehicle.damping_n_s_per_m
    for i, seg in enumerate(route.segments):
        idx = np.flatnonzero(trace.segment == i)
        if not len(idx):
            continue
        sel = idx[settle:] if len(idx) > settle else idx[-1:]
        act = {"ba_rms_mps2": rms(a["ba"][sel]), "sws_rms_m": rms(a["sws"][sel]),
               "dtd_rms_m": rms(a["dtd"][sel]), "force_rms_n": rms(a["force"][sel])}
        pas = {"ba_rms_mps2": rms(a["p_ba"][sel]), "sws_rms_m": rms(a["p_sws"][sel]),
               "dtd_rms_m": rms(a["p_dtd"][sel]), "force_rms_n": 0.0}
        hits = int(np.count_nonzero(a["grade_est"][sel] == trace.true_grade[sel]))
        acc_hits += hits
        acc_n += len(sel)
        t = len(sel) * dt
        first, last_i = sel[0], sel[-1]
        harvested = float(a["stored"][last_i] - a["stored"][first - 1 if first else 0])
        consumed = float(a["drawn"][last_i] - a["drawn"][first - 1 if first else 0])
        road_power = c_s * float(np.mean(a["p_vrel"][sel] ** 2))
        segments.append({
            "grade": seg.grade, "speed_mps": seg.speed_mps, "duration_s": seg.duration_s(),
            "active": act, "passive": pas,
            "ratio": {k: act[f"{k}_rms_{u}"] / pas[f"{k}_rms_{u}"]
                      for k, u in (("ba", "mps2"), ("sws", "m"), ("dtd", "m"))},
            "grade_accuracy": hits / len(sel),
            "harvested_j": harvested, "consumed_j": consumed,
            "harvested_w": harvested / t, "road_power_w": road_power,
            "road_estimate_rmse_m": rms(a["road_est"][sel] - a["zf"][sel]),
        })
    modes_seq = a["mode"]
    switches = int(np.count_nonzero(modes_seq[1:] != modes_seq[:-1]))
    grades_seq = [s.grade for s in route.segments]
    grade_changes = sum(1 for x, y in zip(grades_seq, grades_seq[1:]) if min(3, GRADES.index(x)) != min(3, GRADES.index(y)))
    return {
        "route": route.name, "mode": mode, "controller": controller, "seed": seed,
        "vehicle": cfg.source, "duration_s": len(trace.segment) * dt,
        "segments": segments,
        "grade_accuracy": acc_hits / acc_n if acc_n else float("nan"),
        "mode_switches": switches, "grade_changes": grade_changes, "settle_s": SETTLE_S,
        "trace_sha256": digest,
        "energy": plant.ledger.as_dict(),
        "akf_r_guard_hits": state.akf.guard_hits,
    }
