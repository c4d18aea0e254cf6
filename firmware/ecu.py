"""The ECU: one deterministic fixed-step function, ``step(state, inputs) -> (state, outputs)``.

Order of one tick (fixed; each stage uses what the previous ones produced):
  1. ADC sampling: counts -> SI, plausibility -> fault bits          (adc)
  2. road and state estimation with the force that acted as input    (akf, uses 1)
  3. road-grade estimate and road-holding check                      (grade, uses 2)
  4. mode state machine: recommendation, driver decision, overrides  (modes, uses 1, 3)
  5. controller of the active mode, crossfaded on a mode change      (control, uses 1-4)
  6. actuator stage: force -> current -> voltage -> PWM duty / regen (actuator, uses 5)
  7. status values
Time enters only as the tick count in the inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from firmware import actuator, adc, akf, fixed, grade, modes, safety
from firmware.control import bppid, pid, regen
from firmware.params import (CTRL_BPPID, CTRL_GALQR, CTRL_LQR, CTRL_NONE, CTRL_PID, CTRL_REGEN,
                             CTRL_SKYHOOK, MODE_ENERGY, MODE_PASSIVE, EcuParams)
from firmware.fixedpoint import to_fixed, to_float

# fault word: low byte = ADC channels (firmware.adc.FAULT_BIT); higher bits:
FAULT_NONFINITE_ESTIMATE = 1 << 8   # the estimator diverged (reset, fail-safe this tick)
FAULT_INVALID_REQUEST = 1 << 9      # driver request with an invalid mode (informational)
# bit 7 (safety.FAULT_RATE): a message or a driver request came too often (ignored); 10-15: frame
# validity of the receive path (safety.FAULT_*)
FAULT_NAMES = {**{bit: name for name, bit in adc.FAULT_BIT.items()},
               safety.FAULT_RATE: "rate", FAULT_NONFINITE_ESTIMATE: "estimator_reset",
               FAULT_INVALID_REQUEST: "invalid_request", safety.FAULT_DLC: "dlc",
               safety.FAULT_CHECKSUM: "checksum", safety.FAULT_COUNTER: "counter",
               safety.FAULT_TIMEOUT: "timeout", safety.FAULT_UNKNOWN_ID: "unknown_id",
               safety.FAULT_RANGE: "range"}


def fault_names(word: int) -> list[str]:
    """The names of the bits set in a fault word (lowest bit first)."""
    return [name for bit, name in sorted(FAULT_NAMES.items()) if word & bit]


# channels whose loss makes active control unsafe
SAFETY_RELEVANT = (adc.FAULT_BIT["body_accel"] | adc.FAULT_BIT["wheel_accel"]
                   | adc.FAULT_BIT["susp_defl"] | adc.FAULT_BIT["motor_current"]
                   | adc.FAULT_BIT["speed"] | FAULT_NONFINITE_ESTIMATE)


# Inputs and Outputs are immutable records; as NamedTuples they are built in 0.5 us each
# (as frozen dataclasses: 1.4 and 2.0 us, every tick).
class Inputs(NamedTuple):
    tick: int
    body_accel: int | None   # ADC counts (None: no valid sample this tick -> channel fault)
    wheel_accel: int | None
    susp_defl: int | None
    motor_current: int | None
    speed: int | None
    req_kind: int = 0        # latest driver request (REQ_*)
    req_mode: int = 0
    req_counter: int = 0
    link_faults: int = 0     # frame-validity fault bits (firmware.safety.FAULT_*) of the
    #                          receive path; a channel whose frame was invalid arrives as None


# the ADC takes the counts as inputs[1:6]
assert Inputs._fields[1:6] == adc.CHANNELS


class Outputs(NamedTuple):
    duty_q15: int            # signed PWM duty
    regen: bool              # regen switch: bridge DC side to the storage element
    enable: bool             # bridge enable
    recommended_mode: int
    active_mode: int
    grade: int               # 0..3 = A..D, 255 unknown
    faults: int
    reason: int              # why the active mode differs from the driver's (modes.REASON_*)
    events: int              # driver-request events of this tick (modes.EVT_*)
    override: bool
    # status values, quantised as they are sent (integers)
    force_cmd_n: int
    road_est_um: int         # road height estimate, micrometres
    dtd_est_um: int          # tyre deflection estimate, micrometres
    gq_est_log_c: int        # log4(G_q / G_q,A) * 100 (A = 0, B = 100, ...), -32768 if unknown
    ba_rms_mmps2: int        # body acceleration RMS over the grade window, mm/s^2
    dtd_rms_um: int          # tyre deflection RMS (road-holding check), micrometres


@dataclass
class EcuState:
    params: EcuParams
    adc: adc.AdcState
    akf: akf.AkfState
    grade: grade.GradeState
    modes: modes.ModeState
    actuator: actuator.ActuatorState
    bppid: bppid.BpPidState
    pid: pid.PidState
    ctrl: int = CTRL_NONE            # controller now driving
    ctrl_from: int = CTRL_NONE       # controller being faded out
    ramp: int = 0                    # ticks into the crossfade
    force_meas_prev: float = 0.0     # force from the measured current, last tick
    dtd2_ema: float = 0.0            # tyre-deflection mean square (road-holding check)
    road_per_mps: float = 0.0        # the AKF's road intensity per m/s ...
    road_per_mps_gq: object = None   # ... computed for this G_q object (None: not yet)
    tick: int = -1
    fx_tables: fixed.FxTables | None = None   # fixed-point control path (None: float)
    fx: fixed.FxState | None = None
    fx_log: list | None = None       # (fixed.TickIn, fixed.outputs) per tick, when recording


def init(params: EcuParams, fixed_point: bool = False, record: bool = False) -> EcuState:
    """The ECU's state. ``fixed_point``: the control path in integer arithmetic
    (``firmware.fixed``) instead of float; ``record``: keep its per-tick inputs and outputs
    (the trace the C parity test replays)."""
    st = EcuState(params=params, adc=adc.AdcState(), akf=akf.init(params.akf),
                  grade=grade.GradeState(), modes=modes.init(params.modes),
                  actuator=actuator.ActuatorState(), bppid=bppid.init(params.control),
                  pid=pid.PidState())
    st.ctrl = params.modes.controllers[st.modes.active_mode]
    if fixed_point:
        st.fx_tables = fixed.build_tables(params)
        st.fx = fixed.init(st.fx_tables, st.ctrl)
        st.fx_log = [] if record else None
    return st


FX_CHANNELS = ("body_accel", "wheel_accel", "susp_defl", "motor_current")


def _estimate_fixed(st: EcuState, road_intensity: float) -> tuple:
    """Steps 2 of the fixed-point path: integer prediction and correction of x around the
    float covariance/gain update. Returns (x as float, the TickIn parts so far)."""
    P, T, fs = st.params, st.fx_tables, st.fx
    counts = tuple(st.adc.channels[n].counts for n in FX_CHANNELS)
    resid_q = fixed.measure(T, fs, counts)
    akf.predict_cov(P.akf, st.akf, road_intensity)
    r_q = [to_fixed(float(v), fixed.MEAS_FRAC[j]) if math.isfinite(v) else 0
           for j, v in enumerate(st.akf.r)]
    resid = np.array([to_float(v, fixed.MEAS_FRAC[j]) for j, v in enumerate(resid_q)])
    K, _ = akf.gain(P.akf, st.akf, resid)
    k_q = fixed.quantize_gain(T, fs, K)
    fixed.correct(T, fs, k_q, r_q)
    st.akf.x = np.array([to_float(v, f) for v, f in zip(fs.x, fixed.STATE_FRAC)])
    return counts, tuple(k_q), tuple(r_q), False


def _force_of(st: EcuState, ctrl: int, x: np.ndarray, ba: float) -> float:
    p = st.params.control
    dt = st.params.dt_s
    if ctrl == CTRL_LQR:
        return -float(p.k_safety @ x)
    if ctrl == CTRL_GALQR:
        return -float(p.k_comprehensive @ x)
    if ctrl == CTRL_SKYHOOK:
        return -p.skyhook_c * x[0] - p.skyhook_passive_c * (x[0] - x[1])
    if ctrl == CTRL_PID:
        return pid.step(st.pid, -ba, p.pid_kp, p.pid_ki, p.pid_kd, p.pid_leak, dt, p.force_limit)
    if ctrl == CTRL_BPPID:
        return bppid.step(p, st.bppid, ba, dt)
    if ctrl == CTRL_REGEN:
        return regen.force(p, x[0], x[0] - x[1])
    return 0.0


def step(st: EcuState, inp: Inputs) -> tuple[EcuState, Outputs]:
    P = st.params
    plant = P.plant
    st.tick = inp.tick
    # 1. ADC
    (ba, wa, defl, i_meas, speed), faults = adc.sample_counts(P.adc, st.adc, inp[1:6])
    faults |= inp.link_faults
    # 2. AKF
    # road intensity for the process noise: the grade estimate's G_q once there is one
    # (Sage-Husa adaptation of R needs Q about right on smooth roads, where sensor noise
    # matters), capped at the calibrated nominal (a larger Q on rough roads only adds
    # estimation noise: measured on D roads, SWS 0.79 instead of 0.76 in comprehensive mode)
    gq = st.grade.gq
    if gq is not st.road_per_mps_gq:     # (G_q changes once per grade block)
        if P.akf_q_follows_grade and math.isfinite(gq):
            lo, hi = P.grade.gq_centres[0] * 0.5, P.akf_q_gq_nominal
            st.road_per_mps = (P.akf.road_intensity_per_mps * min(hi, max(lo, gq))
                               / P.akf_q_gq_nominal)
        else:
            st.road_per_mps = P.akf.road_intensity_per_mps
        st.road_per_mps_gq = gq
    road_per_mps = st.road_per_mps
    if st.fx is None:
        # the force acting now, from the measured current (direction picks the efficiency)
        x_prev = st.akf.x
        rel_prev = x_prev.item(0) - x_prev.item(1)
        g = plant.efficiency if i_meas * rel_prev >= 0.0 else 1.0 / plant.efficiency
        force_meas = g * plant.force_constant * i_meas
        # z = [BA, SWS] or [BA, SWS, WA]
        finite = akf.tick(P.akf, st.akf, 0.5 * (st.force_meas_prev + force_meas),
                          road_per_mps * speed, ba, defl, wa, force_meas)
    else:
        fx_in = _estimate_fixed(st, road_per_mps * speed)
        force_meas = to_float(st.fx.force_meas, fixed.F_FORCE)
        finite = akf.all_finite(st.akf.x, st.akf.P)
    st.force_meas_prev = force_meas
    x = st.akf.x
    if not finite:
        faults |= FAULT_NONFINITE_ESTIMATE
        st.akf = akf.init(P.akf)
        x = st.akf.x
        if st.fx is not None:
            fixed.reset_estimate(st.fx)
            fx_in = (*fx_in[:3], True)
    vs, vt, _, zt, zf = x.tolist()   # (Python floats: faster arithmetic than numpy scalars)
    # 3. grade and road-holding
    dtd_est = zt - zf
    g_est = grade.step(P.grade, st.grade, vt, dtd_est, ba, speed, P.dt_s)
    alpha = 1.0 / P.modes.safety_window_ticks
    st.dtd2_ema += alpha * (dtd_est * dtd_est - st.dtd2_ema)
    dtd_rms = math.sqrt(st.dtd2_ema)
    # 4. modes
    safety_fault = bool(faults & SAFETY_RELEVANT)
    mode = modes.step(P.modes, st.modes, g_est, inp.req_kind, inp.req_mode, inp.req_counter,
                      dtd_rms, safety_fault)
    if st.modes.events & modes.EVT_INVALID_REQUEST:
        faults |= FAULT_INVALID_REQUEST
    if st.modes.events & modes.EVT_REQUEST_RATE:
        faults |= safety.FAULT_RATE
    # 5./6. control and actuator
    regen_on = mode == MODE_ENERGY
    if st.fx is not None:
        return st, _finish(st, *_control_fixed(st, mode, safety_fault, regen_on, fx_in),
                           regen_on, mode, g_est, faults, zf, dtd_est, dtd_rms)
    # 5. control, with a crossfade when the controller changes (bumpless transfer)
    want = P.modes.controllers[mode]
    if want != st.ctrl:
        st.ctrl_from, st.ctrl, st.ramp = st.ctrl, want, 0
        if want in (CTRL_PID, CTRL_BPPID):
            pid.reset_to(st.pid if want == CTRL_PID else st.bppid.pid, 0.0)
    force = _force_of(st, st.ctrl, x, ba)
    if st.ramp < P.modes.ramp_ticks:
        st.ramp += 1
        beta = st.ramp / P.modes.ramp_ticks
        force = beta * force + (1.0 - beta) * _force_of(st, st.ctrl_from, x, ba)
    lim = P.control.force_limit
    force = min(lim, max(-lim, force))
    # 6. actuator
    active = (mode != MODE_PASSIVE or st.ramp < P.modes.ramp_ticks) and not safety_fault
    rel = vs - vt
    if active:
        i_ref = actuator.current_reference(plant, force, rel, compensate=not regen_on)
        # relative acceleration over the tick: measured now, plus the change of force
        rel_acc = (ba - wa) + (force - force_meas) * (1.0 / plant.ms + 1.0 / plant.mt)
        duty = actuator.step(P.actuator, plant, st.actuator, i_ref, i_meas, rel, regen_on,
                             P.control.regen_min_voltage_ratio, rel_acc, P.dt_s)
    else:
        actuator.reset(st.actuator)
        duty, force = 0, 0.0
    return st, _finish(st, duty, active, force, regen_on, mode, g_est, faults, zf, dtd_est,
                       dtd_rms)


def _control_fixed(st: EcuState, mode: int, safety_fault: bool, regen_on: bool,
                   fx_in: tuple) -> tuple:
    T, fs = st.fx_tables, st.fx
    want = st.params.modes.controllers[mode]
    duty, active, force_q = fixed.control(T, fs, want, mode == MODE_PASSIVE, safety_fault, regen_on)
    st.ctrl, st.ctrl_from, st.ramp = fs.ctrl, fs.ctrl_from, fs.ramp
    if st.fx_log is not None:
        counts, k_q, r_q, reset = fx_in
        st.fx_log.append((fixed.TickIn(counts, k_q, r_q, want, mode == MODE_PASSIVE,
                                       safety_fault, regen_on, reset), fixed.outputs(fs)))
    return duty, active, to_float(force_q, fixed.F_FORCE)


def _finish(st: EcuState, duty: int, active: bool, force: float, regen_on: bool, mode: int,
            g_est: int, faults: int, road_est: float, dtd_est: float, dtd_rms: float) -> Outputs:
    # 7. status (positional: Outputs' field order)
    gq_log = st.grade.log_gq
    ms = st.modes
    rha = actuator.round_half_away
    return Outputs(
        duty, regen_on and active, active, ms.recommended, mode, g_est, faults, ms.reason,
        ms.events, ms.override, rha(force), rha(road_est * 1e6), rha(dtd_est * 1e6),
        rha(gq_log * 100) if math.isfinite(gq_log) else -32768, rha(st.grade.ba_rms * 1e3),
        rha(dtd_rms * 1e6))
