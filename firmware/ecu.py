"""The ECU: one deterministic fixed-step tick, compiled (numba), ``tick(P, T, S, inp, out)``
over records with named fields (``firmware.layout``): the calibration ``P``, the fixed-point
path's tables ``T`` (None: the float path; numba compiles each variant with the other's
branch pruned), the state ``S`` (one record, a sub-record per stage), one tick's inputs and
outputs. ``tick`` reads top to bottom, one stage per comment line: what it uses, what it
gives. Time enters only as the tick count in the inputs. The same source runs in the
interpreter with ``NUMBA_DISABLE_JIT=1`` and gives the same bits.

Stages: 1 ``firmware.adc``, 2 ``firmware.akf`` (or the fixed-point path's integer half,
``firmware.fx.path``), 2b ``firmware.diag.fdi``, 3 ``firmware.grade``, 4 ``firmware.modes``,
5-6 ``firmware.control`` and ``firmware.actuator`` (or ``firmware.fx.path``), 7 the outputs,
8 ``firmware.diag.dtc``.

``Ecu`` is the handle the bench holds: ``step(Inputs) -> Outputs``, the diagnostic memory for
the UDS server (``diag``: ``firmware.diag.view``), an ECU reset.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from firmware import actuator, adc, akf, control, grade, modes, safety
from firmware.diag import bank, degrade, dtc, fdi
from firmware.diag.fdi import SUPPLY_TESTS
from firmware.diag.view import DiagView
from firmware.fixedpoint import to_float
from firmware.fx import estimate as fx_estimate
from firmware.fx import path as fx
from firmware.fx.state import TickIn
from firmware.fx.tables import F_FORCE
from firmware.kernels import INTERPRETED, njit
from firmware.layout import INPUTS, OUTPUTS, params_record, record, view
from firmware.modes import EVT_INVALID_REQUEST, EVT_REQUEST_RATE
from firmware.params import MODE_ENERGY, MODE_PASSIVE, EcuParams
from firmware.util import round_half_away as rha


# Inputs and Outputs: one tick's, as the bench's Python hands them over (``Ecu.step``); the
# compiled tick reads and writes the records ``layout.INPUTS``/``OUTPUTS``.
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
    degraded: int = 0        # firmware.diag.degrade.STATE_* (ECU_STATUS.DEGRADED)


# an ADC channel or a frame of the receive path was bad: the filter ran on held values
INPUT_FAULTS = (sum(adc.FAULT_BIT.values()) | safety.FAULT_DLC | safety.FAULT_CHECKSUM
                | safety.FAULT_COUNTER | safety.FAULT_TIMEOUT | safety.FAULT_RANGE)


LAST = np.dtype([   # the last tick's values the DIDs and the next snapshot read
    ("mode", "i8"), ("grade", "i8"), ("faults", "i8"),
    ("speed", "i8"),            # VEHICLE_SPEED's counts (0xFFFF: none)
    ("ba_rms_mmps2", "i8"), ("dtd_rms_um", "i8"), ("tick", "i8"),
    ("supply_mv", "i8"),        # 0xFFFF: not measured yet
])


def state_dtype(p: EcuParams) -> np.dtype:
    """The ECU's state for calibration ``p`` (array sizes follow it)."""
    m = p.akf.H.shape[0]
    n_hidden, n_in = p.control.bp_w_hidden.shape
    return np.dtype([
        ("tick", "i8"),
        ("adc", adc.STATE), ("akf", akf.state_dtype(m)),
        ("grade", grade.state_dtype(p.grade.n_blocks)), ("modes", modes.STATE),
        ("ctl", control.state_dtype(n_in, n_hidden, p.control.bp_w_out.shape[0])),
        ("fdi", fdi.STATE), ("bank", bank.STATE), ("degrade", degrade.STATE),
        ("dtc", dtc.STATE), ("last", LAST),
        ("snapshot", "i8", (len(dtc.SNAPSHOT),)),    # (the freeze frame being taken)
        ("good_counts", "i8", (4,)),                 # (stage 2b's: BA, WA, SWS, current)
        ("fx", fx.state_dtype(m)),                   # the fixed-point path's integer state
        ("resid_f", "f8", (m,)),                     # (its residual as floats)
    ])


def init(p: EcuParams, P: np.ndarray | None = None, T: np.ndarray | None = None
         ) -> np.ndarray:
    """A new ECU's state record for calibration ``p`` (``P``: its record, if made; ``T``: the
    fixed-point tables' record, for that path)."""
    P = params_record(p) if P is None else P
    S = record(state_dtype(p))
    s, c = view(S), view(P)
    s.tick = -1
    adc.init(s.adc)
    akf.init(P[0]["akf"], S[0]["akf"])
    grade.init(s.grade)
    modes.init(c.modes, s.modes)
    control.init(c.control, s.ctl, p.modes.controllers[p.modes.initial_mode])
    fdi.init(s.fdi)
    bank.init(s.bank)
    degrade.init(s.degrade)
    dtc.init(s.dtc)
    if T is not None:
        fx.init(view(T), s.fx, p.modes.controllers[p.modes.initial_mode])
    s.last.grade, s.last.speed, s.last.tick, s.last.supply_mv = 255, 0xFFFF, -1, 0xFFFF
    return S


def inputs() -> np.ndarray:
    return record(INPUTS)


def outputs() -> np.ndarray:
    return record(OUTPUTS)


@njit
def tick(Pa, Ta, Sa, ia, oa) -> None:
    """One ECU tick: inputs ``ia[0]`` -> outputs ``oa[0]``, state ``Sa[0]`` updated; ``Ta``:
    the fixed-point tables (None: the float path)."""
    P, S, inp, out = Pa[0], Sa[0], ia[0], oa[0]
    S.tick = inp.tick
    # 1. ADC: the inputs' counts -> SI values, channel faults (held values on a fault; a rail
    #    the last estimate explains is none); a sensor out (firmware.diag.degrade): its
    #    channel is the virtual sensor's
    counts = degrade.substitute(P, S, inp.counts)
    faults = adc.sample(P.adc, S.adc, counts, _explained_rails(P, S))
    ba, wa, defl = S.adc.value[adc.BA], S.adc.value[adc.WA], S.adc.value[adc.DEFL]
    i_meas, speed = S.adc.value[adc.CUR], S.adc.value[adc.SPEED]
    faults |= inp.link_faults
    if adc.unsettled(P.adc, S.adc):      # no sample this tick, or recovering from one
        faults |= safety.FAULT_SAMPLE
    # 2. AKF: predict with the force from the measured current, correct with [BA, SWS, WA]
    #    (uses 1 and the grade's G_q) -> estimate S.akf.x; a non-finite one is reset
    road_intensity = akf.road_per_mps(P, S.grade.gq) * speed
    if Ta is None:
        force_meas, finite = akf.estimate(P, S, ba, wa, defl, i_meas, road_intensity)
    else:
        force_meas, finite = fx_estimate.estimate(P, Ta[0], S, ba, wa, road_intensity)
    if not finite:
        faults |= safety.FAULT_NONFINITE_ESTIMATE
        akf.init(P.akf, S.akf)
        if Ta is not None:
            S.fx.x[:] = 0
            S.fx.reset = True
    degrade.take_out(P, S, inp.tick)      # (a sensor left out by hand: as if named now)
    degrade.known_force(S.degrade, force_meas + akf.bump_force(P.akf, defl))
    vt, zt, zf = S.akf.x[1], S.akf.x[3], S.akf.x[4]
    dtd_est = zt - zf
    # 2b. model-based fault detection: innovation, flatline, actuator, supply tests (uses 1, 2)
    if not finite:
        S.fdi.failed = S.fdi.completed = 0
    else:
        faults |= _fdi(P, S, inp, defl, ba, wa, i_meas, force_meas, faults)
    # 3. road grade from the road estimate (uses 1, 2); tyre-deflection RMS for road holding
    g_est = grade.step(P.grade, S.grade, vt, dtd_est, ba, speed, P.dt_s)
    dtd_rms = modes.road_holding_rms(P.modes, S.modes, dtd_est)
    # 4. modes: recommendation, driver request, safety override, fail-safe, the modes a
    #    sensor out keeps (uses 1-3)
    safety_fault = (faults & P.safety_relevant) != 0
    mode = modes.step(P.modes, S.modes, g_est, inp.req_kind, inp.req_mode, inp.req_counter,
                      dtd_rms, safety_fault, degrade.kept_modes(P, S))
    faults |= _request_faults(S.modes.events)
    # 5.-6. controller of the mode, crossfaded; the gate; force -> PWM duty / regen (uses 1-4)
    regen_on = mode == MODE_ENERGY
    if Ta is None:
        duty, active, force = _control(P, S, mode, safety_fault, regen_on, ba, wa, i_meas,
                                       force_meas)
    else:
        duty, active, force = _control_fixed(P, Ta[0], S, mode, safety_fault, regen_on)
    # 7. outputs, quantised as sent (uses 1-6)
    _outputs(S, out, duty, active, force, regen_on, mode, g_est, faults, zf, dtd_est, dtd_rms)
    # 8. diagnostics: the command for the actuator test, the DTC memory (uses 1-7)
    _diagnostics(P, S, inp, out, duty, mode, g_est, faults)


@njit
def _explained_rails(P, S) -> int:
    """Stage 1's explained rails: the motor current's while the last estimate's relative
    velocity is one at which the back-EMF alone drives the current past its sensor's range
    (``AdcParams.current_rail_mps``); the deflection sensor's while the last estimate's
    stroke is at its rail (``AdcParams.defl_rail_margin_m``: the filter does not take a
    clipped stroke as a measurement, so a sensor stuck at its rail leaves it inside)."""
    out = 0
    if abs(S.akf.x[0] - S.akf.x[1]) >= P.adc.current_rail_mps:
        out |= 1 << adc.CUR
    A, d = P.adc, adc.DEFL
    lo = A.range_min[d] + A.defl_rail_margin_m
    hi = A.range_min[d] + A.full_scale[d] * A.lsb[d] - A.defl_rail_margin_m
    stroke = S.akf.x[2] - S.akf.x[3]
    if stroke <= lo or stroke >= hi:
        out |= 1 << d
    return out


@njit
def _request_faults(events: int) -> int:
    """The fault bits of a tick's driver-request events (``firmware.modes.EVT_*``)."""
    out = 0
    if events & EVT_INVALID_REQUEST:
        out |= safety.FAULT_INVALID_REQUEST
    if events & EVT_REQUEST_RATE:
        out |= safety.FAULT_RATE
    return out


@njit
def _outputs(S, out, duty, active, force, regen_on, mode, g_est, faults, zf, dtd_est,
             dtd_rms) -> None:
    """Stage 7: the outputs, the status values quantised as they are sent (integers)."""
    out.duty_q15, out.regen, out.enable = duty, regen_on and active, active
    out.recommended_mode, out.active_mode, out.grade = S.modes.recommended, mode, g_est
    out.faults, out.reason, out.events = faults, S.modes.reason, S.modes.events
    out.override = S.modes.override
    out.force_cmd_n, out.road_est_um = rha(force), rha(zf * 1e6)
    out.dtd_est_um = rha(dtd_est * 1e6)
    gq_log = S.grade.log_gq
    out.gq_est_log_c = rha(gq_log * 100) if math.isfinite(gq_log) else -32768
    out.ba_rms_mmps2, out.dtd_rms_um = rha(S.grade.ba_rms * 1e3), rha(dtd_rms * 1e6)
    out.degraded = degrade.state_code(S.degrade)


@njit
def _control(P, S, mode, fault, regen, ba, wa, i_meas, force_meas):
    """Stages 5-6 of the float path: the controller's force, the final gate (active force
    only in an active mode, or while a crossfade into passive runs, and never with a
    safety-relevant fault; else the bridge opens and passive damping remains), the actuator
    stage. Returns (duty_q15, enable, force)."""
    pl, x, n = P.plant, S.akf.x, P.modes.ramp_ticks
    force = control.command(P.control, S.ctl, P.modes.controllers[mode], n, x, ba, P.dt_s)
    if not ((mode != MODE_PASSIVE or S.ctl.ramp < n) and not fault):   # the final gate
        actuator.reset(S.ctl.actuator)
        return 0, False, 0.0
    rel = x[0] - x[1]
    i_ref = actuator.current_reference(pl, P.actuator, force, rel, not regen)
    # relative acceleration over the tick: measured now, plus the change of force
    rel_acc = (ba - wa) + (force - force_meas) * (1.0 / pl.ms + 1.0 / pl.mt)
    duty = actuator.step(P.actuator, pl, S.ctl.actuator, i_ref, i_meas, rel, regen,
                                 P.control.regen_min_voltage_ratio, rel_acc, P.dt_s)
    return duty, True, force


@njit
def _control_fixed(P, T, S, mode, fault, regen):
    """Stages 5-6 of the fixed-point path (``firmware.fx.path.control``: the same gate)."""
    F = S.fx
    F.want, F.passive, F.fault, F.regen = P.modes.controllers[mode], mode == MODE_PASSIVE, \
        fault, regen
    duty, active, force_q = fx.control(T, F, F.want, F.passive, fault, regen)
    return duty, active, to_float(force_q, F_FORCE)


@njit
def _fdi(P, S, inp, defl, ba, wa, i_meas, force_meas, faults) -> int:
    """Stage 2b: the fault-word bits of the failed tests (a failed supply test is the supply
    bit, any other the plausibility bit)."""
    gq = S.grade.gq
    rho = gq / P.akf_q_gq_nominal if math.isfinite(gq) and gq > P.akf_q_gq_nominal else 1.0
    lifted = akf.airborne(P.akf, P.plant.ms, P.plant.mt, ba, wa)
    good = S.good_counts
    for c in range(4):
        good[c] = adc.good_count(S.adc, c) if c != S.degrade.sensor else -1
    inputs_ok = not (faults & INPUT_FAULTS)
    failed = fdi.step(P, S.fdi, inp.tick, S.akf.innovation, S.akf.hph, rho, force_meas, good,
                      defl, lifted, i_meas, ba - wa, inputs_ok, inp.supply,
                      S.degrade.sensor != adc.BA and S.degrade.sensor != adc.WA)
    failed = degrade.silence(S, failed)               # (a sensor out's own tests)
    bank.isolate(P, S, inp.tick, ba, wa, defl, i_meas, force_meas, lifted, inputs_ok, failed,
                 _freeze_frame(S, inp.tick))
    # a sensor named: degraded operation (its own tests silent from the next tick); a second
    # fault latches the fail-safe (the plausibility bit held); a sensor out well again
    degrade.step(P, S, inp.tick)
    degrade.watch(P, S, force_meas, rho)
    blocked = degrade.bridge_blocked(S)
    return ((safety.FAULT_PLAUSIBILITY if failed & ~SUPPLY_TESTS or blocked else 0)
            | (safety.FAULT_SUPPLY if failed & SUPPLY_TESTS else 0))


@njit
def _freeze_frame(S, tick: int):
    """The snapshot a failure this tick takes (``dtc.SNAPSHOT``): the last tick's view, the
    supply as last measured."""
    v, snap = S.last, S.snapshot
    snap[0], snap[1], snap[2], snap[3] = tick, v.speed, v.grade, v.mode
    snap[4], snap[5], snap[6] = v.ba_rms_mmps2, v.dtd_rms_um, supply_mv(S.fdi.supply_v)
    return snap


@njit
def supply_mv(volts: float) -> int:
    """The supply voltage as the DIDs and snapshots carry it: mV, 0xFFFF not measured yet."""
    if math.isnan(volts):
        return 0xFFFF
    return min(0xFFFE, max(0, rha(volts * 1000.0)))


@njit
def _diagnostics(P, S, inp, out, duty, mode, g_est, faults) -> None:
    """Stage 8: the tick's command for the actuator test, the DTC memory's reports (a first
    failure's snapshot: the last tick's view, the supply as last measured), and the values
    the DIDs and the next snapshot read."""
    fdi.command(P, S.fdi, duty, out.enable, out.regen)
    v = S.last
    # (a decision of the isolation bank keeps the freeze frame of its detection)
    snap = S.bank.snapshot if S.bank.reported else _freeze_frame(S, inp.tick)
    dtc.update(S.dtc, inp.tick, faults, S.fdi.failed, S.fdi.completed, snap)
    speed = inp.counts[adc.SPEED]
    v.mode, v.grade, v.faults = mode, g_est, faults
    v.speed = 0xFFFF if speed < 0 else speed
    v.ba_rms_mmps2, v.dtd_rms_um, v.tick = out.ba_rms_mmps2, out.dtd_rms_um, inp.tick
    v.supply_mv = supply_mv(S.fdi.supply_v)


@njit
def tick_values(Pa, Ta, Sa, ia, oa, k, c0, c1, c2, c3, c4, supply, kind, mode, counter,
                link):
    """``tick`` with the inputs as numbers (counts and supply -1 for none) and the outputs
    returned in ``firmware.ecu.Outputs``' order: the call the bench's ECU node makes."""
    inp = ia[0]
    inp.tick = k
    inp.counts[0], inp.counts[1], inp.counts[2], inp.counts[3], inp.counts[4] = \
        c0, c1, c2, c3, c4
    inp.supply, inp.req_kind, inp.req_mode, inp.req_counter = supply, kind, mode, counter
    inp.link_faults = link
    tick(Pa, Ta, Sa, ia, oa)
    o = oa[0]
    return (o.duty_q15, o.regen != 0, o.enable != 0, o.recommended_mode, o.active_mode,
            o.grade, o.faults, o.reason, o.events, o.override != 0, o.force_cmd_n,
            o.road_est_um, o.dtd_est_um, o.gq_est_log_c, o.ba_rms_mmps2, o.dtd_rms_um,
            o.degraded)


@njit
def new_cycle(Sa) -> None:
    """``firmware.diag.dtc.new_cycle`` on the state record's DTC memory."""
    dtc.new_cycle(Sa[0].dtc)


def _counts(c) -> int:
    """An input's counts as the record holds them: ``adc.NO_SAMPLE`` for None (no sample),
    ``adc.INVALID`` where it is no valid sample (not an int, a bool, or an int beyond any
    channel's range: the ADC stage's fault)."""
    if c is None:
        return adc.NO_SAMPLE
    if isinstance(c, int) and not isinstance(c, bool) and 0 <= c < 1 << 31:
        return c
    return adc.INVALID


class Ecu:
    """One ECU: calibration ``params``, the fixed-point path with ``tables`` (its
    ``FxTables``; None: float). ``record``: keep the fixed-point path's per-tick hand-over
    and integers (``log``: ``(firmware.fx.state.TickIn, outputs)`` per tick, the C parity
    trace)."""

    def __init__(self, params: EcuParams, tables=None, record: bool = False):
        self.params, self.tables = params, tables
        self.P = params_record(params)
        self.T = params_record(tables) if tables is not None else None
        self.arithmetic = "float" if tables is None else "fixed"
        self.log = [] if record and tables is not None else None
        self.I, self.O = inputs(), outputs()
        self._new_state()

    def _new_state(self) -> None:
        self.S = init(self.params, self.P, self.T)
        self.rec = view(self.S)
        self.diag = DiagView(self.S)

    def __getattr__(self, name):
        """The state's stages as attributes (``ecu.modes.active_mode``, ``ecu.akf.x``:
        numpy records, read and written through)."""
        if name in ("S", "rec") or name.startswith("__"):
            raise AttributeError(name)
        try:
            return getattr(self.rec, name)
        except AttributeError:
            raise AttributeError(f"Ecu has no attribute {name!r}") from None

    def step(self, inp: Inputs) -> Outputs:
        values = tick_values(
            self.P, self.T, self.S, self.I, self.O, inp.tick, _counts(inp.body_accel),
            _counts(inp.wheel_accel), _counts(inp.susp_defl), _counts(inp.motor_current),
            _counts(inp.speed), _counts(inp.supply), inp.req_kind, inp.req_mode,
            inp.req_counter, inp.link_faults)
        if INTERPRETED:       # (numpy's scalars, where numba returns Python's)
            values = tuple(bool(v) if isinstance(v, np.bool_) else int(v) for v in values)
        out = Outputs(*values)
        if self.log is not None:
            self.log.append(self.fx_tick())
        return out

    def fx_tick(self) -> tuple:
        """The fixed-point path's last tick as the C parity trace takes it: its inputs
        (``TickIn``) and the integers C compares (``c/trace_replay.c``)."""
        return fx_entry(self.S[0]["fx"])

    def reset(self) -> None:
        """ECU reset (UDS 0x11): the control state starts again, the DTC memory stays
        (non-volatile) and a new operation cycle begins."""
        kept = self.S[0]["dtc"].copy()
        self._new_state()
        self.S[0]["dtc"] = kept
        new_cycle(self.S)

    def leave_out(self, sensor: str) -> None:
        """From the next tick on, as if the isolation had named ``sensor``
        (``degrade.SENSOR_NAMES``) in it, out to the end of the cycle: how the bench measures
        what the ECU does without it (``tools.degraded``)."""
        degrade.leave_out(self.S, sensor)

    @property
    def tick(self) -> int:
        return int(self.S[0]["tick"])

    @property
    def guard_hits(self) -> int:
        """How often the R-hat guard acted (since the filter last started)."""
        return int(self.S[0]["akf"]["guard_hits"])

    @property
    def gain_saturations(self) -> int:
        return int(self.S[0]["fx"]["gain_saturations"])

    @property
    def x(self) -> np.ndarray:
        """The state estimate [zs', zt', zs, zt, zf] (a view: written through)."""
        return self.S[0]["akf"]["x"]


def fx_entry(f) -> tuple:
    """One tick of the C parity trace from the state's fixed-point hand-over ``S["fx"]``:
    its inputs (``TickIn``) and the integers C compares (``c/trace_replay.c``)."""
    counts = tuple(None if c < 0 else int(c) for c in f["counts"])
    tin = TickIn(counts, tuple(int(v) for v in f["k_q"]), tuple(int(v) for v in f["r_q"]),
                 int(f["want"]), bool(f["passive"]), bool(f["fault"]), bool(f["regen"]),
                 bool(f["reset"]), float(f["q_road"]), int(f["cov_flags"]),
                 tuple(float(v) for v in f["k_f"]))
    return tin, (int(f["duty"]), int(f["force"]), *(int(v) for v in f["x"]),
                 *(int(v) for v in f["resid"]), int(f["integ"]), int(f["voltage"]))
