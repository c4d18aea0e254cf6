"""The ECU: one deterministic fixed-step function, ``step(state, inputs) -> (state, outputs)``.

``init`` takes the arithmetic path once (``firmware.path``: ``FloatPath`` by default, or
``FixedPath``, the integer control path); ``step`` reads top to bottom, one stage per comment line: what it
uses, what it gives. Time enters only as the tick count in the inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from firmware import adc, akf, diag, grade, modes, safety
from firmware.diag import dtc, fdi
from firmware.fixedpoint import round_half_away as rha
from firmware.params import MODE_ENERGY, EcuParams
from firmware.path import FX_CHANNELS, FixedPath, FloatPath


# Inputs and Outputs are immutable records (NamedTuples: built in 0.5 us each, every tick).
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
    supply: int | None = None   # the supply voltage's ADC counts, on a tick a sample arrived


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
    path: FloatPath | FixedPath      # the arithmetic of stages 2 and 5-6
    adc: adc.AdcState
    akf: akf.AkfState
    grade: grade.GradeState
    modes: modes.ModeState
    diag: diag.DiagState = None      # fault detection, DTC memory, UDS session
    road_per_mps: float = 0.0        # the AKF's road intensity per m/s ...
    road_per_mps_gq: object = None   # ... computed for this G_q object (None: not yet)
    tick: int = -1


def init(params: EcuParams, path: FloatPath | FixedPath | None = None) -> EcuState:
    """The ECU's state, with the arithmetic of stages 2 and 5-6: ``path`` (default
    ``FloatPath(params)``; ``FixedPath(params, tables, record)`` runs the control path in
    integers, ``firmware.fx``, with the tables the calibration builds for it)."""
    path = FloatPath(params) if path is None else path
    return EcuState(params=params, path=path, adc=adc.AdcState(), akf=akf.init(params.akf),
                    grade=grade.GradeState(), modes=modes.init(params.modes),
                    diag=diag.DiagState())


def reset(st: EcuState, path: FloatPath | FixedPath) -> EcuState:
    """ECU reset (UDS 0x11): the control state starts again with ``path`` (a fresh one), the
    DTC memory stays (non-volatile) and a new operation cycle begins."""
    new = init(st.params, path)
    new.diag.dtc = st.diag.dtc
    dtc.new_cycle(new.diag.dtc)
    return new


def step(st: EcuState, inp: Inputs) -> tuple[EcuState, Outputs]:
    P, path = st.params, st.path
    st.tick = inp.tick
    # 1. ADC: the inputs' counts -> SI values, channel faults (held values on a fault; a rail
    #    the last estimate explains is none)
    (ba, wa, defl, i_meas, speed), faults = adc.sample(P.adc, st.adc, (
        inp.body_accel, inp.wheel_accel, inp.susp_defl, inp.motor_current, inp.speed),
        _explained_rails(st))
    faults |= inp.link_faults
    # 2. AKF: predict with the force from the measured current, correct with [BA, SWS, WA]
    #    (uses 1 and the grade's G_q) -> estimate st.akf.x; a non-finite one is reset
    force_meas, finite = path.estimate(st, ba, wa, defl, i_meas, _road_per_mps(st) * speed)
    if not finite:
        faults |= safety.FAULT_NONFINITE_ESTIMATE
        path.reset_estimate(st)
    vs, vt, _, zt, zf = st.akf.x.tolist()   # (Python floats: faster arithmetic than numpy's)
    dtd_est = zt - zf
    # 2b. model-based fault detection: innovation, flatline, actuator, supply tests (uses 1, 2)
    if not finite:
        st.diag.fdi.failed = st.diag.fdi.completed = 0
    else:
        faults |= _fdi(st, inp, defl, ba, wa, i_meas, force_meas, faults)
    # 3. road grade from the road estimate (uses 1, 2); tyre-deflection RMS for road holding
    g_est = grade.step(P.grade, st.grade, vt, dtd_est, ba, speed, P.dt_s)
    dtd_rms = modes.road_holding_rms(P.modes, st.modes, dtd_est)
    # 4. modes: recommendation, driver request, safety override, fail-safe (uses 1-3)
    safety_fault = bool(faults & safety.SAFETY_RELEVANT)
    mode = modes.step(P.modes, st.modes, g_est, inp.req_kind, inp.req_mode, inp.req_counter,
                      dtd_rms, safety_fault)
    faults |= safety.request_faults(st.modes.events)
    # 5.-6. controller of the mode, crossfaded; the gate; force -> PWM duty / regen (uses 1-4)
    regen_on = mode == MODE_ENERGY
    duty, active, force = path.control(st, mode, safety_fault, regen_on, ba, wa, i_meas,
                                       force_meas)
    # 7. outputs, quantised as sent (uses 1-6)
    out = _outputs(st, duty, active, force, regen_on, mode, g_est, faults, zf, dtd_est, dtd_rms)
    # 8. diagnostics: the command for the actuator test, the DTC memory (uses 1-7)
    _diagnostics(P, st.diag, inp, out, duty, mode, g_est, faults)
    return st, out


def _explained_rails(st: EcuState) -> int:
    """Stage 1's explained rails (``firmware.adc``): the motor current's while the last
    estimate's relative velocity is one at which the back-EMF alone drives the current past
    its sensor's range (``AdcParams.current_rail_mps``)."""
    x = st.akf.x
    fast = abs(float(x[0]) - float(x[1])) >= st.params.adc.current_rail_mps
    return adc.FAULT_BIT["motor_current"] if fast else 0


def _diagnostics(P: EcuParams, ds: diag.DiagState, inp: Inputs, out: Outputs, duty: int,
                 mode: int, g_est: int, faults: int) -> None:
    """Stage 8: the tick's command for the actuator test, the DTC memory's reports, and the
    values the DIDs and the next snapshot read."""
    fdi.command(P, ds.fdi, duty, out.enable, out.regen)
    dtc.update(ds.dtc, inp.tick, faults, ds.fdi.failed, ds.fdi.completed, ds.snap)
    ds.view = (mode, g_est, faults, 0xFFFF if inp.speed is None else inp.speed,
               out.ba_rms_mmps2, out.dtd_rms_um, inp.tick, diag.supply_mv(ds.fdi.supply_v))


def _fdi(st: EcuState, inp: Inputs, defl: float, ba: float, wa: float, i_meas: float,
         force_meas: float, faults: int) -> int:
    """Stage 2b: the fault-word bits of the failed tests (``firmware.diag.fdi``): a failed
    supply test is the supply bit, any other the plausibility bit."""
    P, k = st.params, st.akf
    gq = st.grade.gq
    rho = gq / P.akf_q_gq_nominal if math.isfinite(gq) and gq > P.akf_q_gq_nominal else 1.0
    lifted = akf.airborne(P.akf, P.plant.ms, P.plant.mt, ba, wa)
    failed = fdi.step(P, st.diag.fdi, inp.tick, k.innovation.tolist(), k.hph.tolist(), rho,
                      force_meas, _good_counts(st), defl, lifted, i_meas, ba - wa,
                      not faults & INPUT_FAULTS, inp.supply)
    return ((safety.FAULT_PLAUSIBILITY if failed & ~fdi.SUPPLY_TESTS else 0)
            | (safety.FAULT_SUPPLY if failed & fdi.SUPPLY_TESTS else 0))


# an ADC channel or a frame of the receive path was bad: the filter ran on held values
INPUT_FAULTS = (sum(adc.FAULT_BIT.values()) | safety.FAULT_DLC | safety.FAULT_CHECKSUM
                | safety.FAULT_COUNTER | safety.FAULT_TIMEOUT | safety.FAULT_RANGE)


def _good_counts(st: EcuState) -> tuple:
    """This tick's counts of BA, WA, SWS, current where the ADC found them good, else None."""
    ch = st.adc.channels
    return tuple(None if c.faulty or c.good_count == 0 else c.counts
                 for c in (ch[name] for name in FX_CHANNELS))


def _road_per_mps(st: EcuState) -> float:
    """The AKF's road intensity per m/s for the process noise: the grade estimate's G_q once
    there is one (Sage-Husa adaptation of R needs Q about right on smooth roads, where sensor
    noise matters), capped at the calibrated nominal (a larger Q on rough roads only adds
    estimation noise: measured on D roads, SWS 0.79 instead of 0.76 in comprehensive mode).
    Recomputed only when the grade's G_q changes (once per grade block)."""
    P, gq = st.params, st.grade.gq
    if gq is not st.road_per_mps_gq:
        if P.akf_q_follows_grade and math.isfinite(gq):
            lo, hi = P.grade.gq_centres[0] * 0.5, P.akf_q_gq_nominal
            st.road_per_mps = (P.akf.road_intensity_per_mps * min(hi, max(lo, gq))
                               / P.akf_q_gq_nominal)
        else:
            st.road_per_mps = P.akf.road_intensity_per_mps
        st.road_per_mps_gq = gq
    return st.road_per_mps


def _outputs(st: EcuState, duty: int, active: bool, force: float, regen_on: bool, mode: int,
             g_est: int, faults: int, road_est: float, dtd_est: float, dtd_rms: float) -> Outputs:
    gq_log = st.grade.log_gq
    ms = st.modes
    return Outputs(   # (positional: Outputs' field order)
        duty, regen_on and active, active, ms.recommended, mode, g_est, faults, ms.reason,
        ms.events, ms.override, rha(force), rha(road_est * 1e6), rha(dtd_est * 1e6),
        rha(gq_log * 100) if math.isfinite(gq_log) else -32768, rha(st.grade.ba_rms * 1e3),
        rha(dtd_rms * 1e6))
