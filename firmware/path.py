"""The ECU's two arithmetic paths, chosen once at ``firmware.ecu.init``: the same stages 2
(estimate) and 5-6 (control, gate, actuator) of a tick, in float (``FloatPath``) or with the
control path in integers (``FixedPath``, ``firmware.fx``, bit-exact with ``c/ecu_fx.c``).

``estimate(st, ba, wa, defl, i_meas, road_intensity) -> (force_meas, finite)`` leaves the new
estimate in ``st.akf.x``; ``reset_estimate(st)`` starts it again after a non-finite one;
``control(st, mode, fault, regen, ba, wa, i_meas, force_meas) -> (duty_q15, enable, force_n)``.
"""

from __future__ import annotations

import math

import numpy as np

from firmware import actuator, adc, akf, control, safety
from firmware.control import fx as fx_control
from firmware.fixedpoint import to_fixed, to_float
from firmware.fx import akf as fx_akf
from firmware.fx import state as fx_state
from firmware.fx.tables import F_FORCE, MEAS_FRAC, STATE_FRAC, FxTables
from firmware.params import CTRL_NAMES, MODE_PASSIVE, EcuParams

FX_CHANNELS = ("body_accel", "wheel_accel", "susp_defl", "motor_current")


def off_model(st, ba: float, wa: float) -> tuple[bool, tuple]:
    """The covariance side of a tick off the linear model (``firmware.akf``), the same in both
    paths: the unknown forces as process noise (a tyre off the road, where the vehicle's can
    lift off; a current or a stroke beyond its sensor's range). Returns whether R_hat may
    adapt (every input a measurement, and the model holds: the innovations of an airborne
    tyre's ticks say nothing about the sensors' noise), and the measurements not to use
    (a faulty channel's held value)."""
    P, m = st.params, st.adc
    current_known = adc.measured(m, ("motor_current",))
    stroke_known = adc.measured(m, ("susp_defl",))
    lifted = akf.airborne(P.akf, P.plant.ms, P.plant.mt, ba, wa) and P.akf.lift_force_sigma_n > 0
    akf.unknown_forces(P.akf, st.akf, lifted, not current_known, not stroke_known)
    held = tuple(j for j, name in enumerate(MEASURED) if m.channels[name].faulty)
    adapt = (current_known and stroke_known and not lifted
             and adc.measured(m, ("body_accel", "wheel_accel")))
    return adapt, held


MEASURED = ("body_accel", "susp_defl", "wheel_accel")    # the filter's z, in its order


class FloatPath:
    name = "float"
    gain_saturations = 0
    log = None

    def __init__(self, params: EcuParams):
        self.ctl = control.init(params.control, params.modes.controllers[params.modes.initial_mode])
        self.actuator = actuator.ActuatorState()
        self.force_known_prev = 0.0      # the known force (actuator, bump stops), last tick

    def estimate(self, st, ba: float, wa: float, defl: float, i_meas: float,
                 road_intensity: float) -> tuple[float, bool]:
        plant = st.params.plant
        # the force acting now, from the measured current (direction picks the efficiency)
        x_prev = st.akf.x
        rel_prev = x_prev.item(0) - x_prev.item(1)
        g = plant.efficiency if i_meas * rel_prev >= 0.0 else 1.0 / plant.efficiency
        force_meas = g * plant.force_constant * i_meas
        # the known force: the actuator's and the bump stops'; the unknown ones as noise
        known = force_meas + akf.bump_force(st.params.akf, defl)
        adapt, held = off_model(st, ba, wa)
        # predict with the force that acted over the tick, correct with z = [BA, SWS(, WA)]
        finite = akf.tick(st.params.akf, st.akf, 0.5 * (self.force_known_prev + known),
                          road_intensity, ba, defl, wa, known, adapt, held)
        self.force_known_prev = known
        return force_meas, finite

    def reset_estimate(self, st) -> None:
        st.akf = akf.init(st.params.akf)

    def control(self, st, mode: int, fault: bool, regen: bool, ba: float, wa: float,
                i_meas: float, force_meas: float) -> tuple[int, bool, float]:
        P, plant, x = st.params, st.params.plant, st.akf.x
        n = P.modes.ramp_ticks
        force = control.command(P.control, self.ctl, P.modes.controllers[mode], n, x, ba,
                                P.dt_s)
        if not safety.force_allowed(mode == MODE_PASSIVE, self.ctl.ramp < n, fault):
            actuator.reset(self.actuator)
            return 0, False, 0.0
        rel = x.item(0) - x.item(1)
        i_ref = actuator.current_reference(plant, force, rel, compensate=not regen)
        # relative acceleration over the tick: measured now, plus the change of force
        rel_acc = (ba - wa) + (force - force_meas) * (1.0 / plant.ms + 1.0 / plant.mt)
        duty = actuator.step(P.actuator, plant, self.actuator, i_ref, i_meas, rel, regen,
                             P.control.regen_min_voltage_ratio, rel_acc, P.dt_s)
        return duty, True, force

    def warm_up(self, st) -> None:
        """Every controller once (on a throwaway copy: numba loads its kernels)."""
        for ctrl in range(len(CTRL_NAMES)):
            control.force_of(st.params.control, self.ctl, ctrl, st.akf.x, 0.1, st.params.dt_s)


class FixedPath:
    name = "fixed"

    def __init__(self, params: EcuParams, tables: FxTables, record: bool = False):
        self.tables = tables
        self.fx = fx_state.init(tables, params.modes.controllers[params.modes.initial_mode])
        self.log = [] if record else None   # (fx.state.TickIn, fx.state.outputs) per tick
        self._in = None

    @property
    def gain_saturations(self) -> int:
        return self.fx.gain_saturations

    def estimate(self, st, ba: float, wa: float, defl: float, i_meas: float,
                 road_intensity: float) -> tuple[float, bool]:
        """Integer prediction and correction of x around the float covariance/gain update."""
        P, T, fs = st.params, self.tables, self.fx
        counts = tuple(st.adc.channels[n].counts for n in FX_CHANNELS)
        resid_q = fx_akf.measure(T, fs, counts)
        adapt, held = off_model(st, ba, wa)
        akf.predict_cov(P.akf, st.akf, road_intensity)
        r_q = [to_fixed(float(v), MEAS_FRAC[j]) if math.isfinite(v) else 0
               for j, v in enumerate(st.akf.r)]
        resid = np.array([to_float(v, MEAS_FRAC[j]) for j, v in enumerate(resid_q)])
        K, _ = akf.gain(P.akf, st.akf, resid, adapt, held)
        k_q = fx_akf.quantize_gain(T, fs, K)
        fx_akf.correct(T, fs, k_q, r_q)
        st.akf.x = np.array([to_float(v, f) for v, f in zip(fs.x, STATE_FRAC)])
        self._in = [counts, tuple(k_q), tuple(r_q), False]
        return to_float(fs.force_meas, F_FORCE), akf.finite(st.akf)

    def reset_estimate(self, st) -> None:
        st.akf = akf.init(st.params.akf)
        fx_akf.reset_estimate(self.fx)
        self._in[3] = True

    def control(self, st, mode: int, fault: bool, regen: bool, ba: float, wa: float,
                i_meas: float, force_meas: float) -> tuple[int, bool, float]:
        want = st.params.modes.controllers[mode]
        passive = mode == MODE_PASSIVE
        duty, active, force_q = fx_control.control(self.tables, self.fx, want, passive, fault, regen)
        if self.log is not None:
            counts, k_q, r_q, reset = self._in
            self.log.append((fx_state.TickIn(counts, k_q, r_q, want, passive, fault, regen,
                                             reset), fx_state.outputs(self.fx)))
        return duty, active, to_float(force_q, F_FORCE)

    def warm_up(self, st) -> None:
        for ctrl in range(len(CTRL_NAMES)):
            fx_control.force_of(self.tables, self.fx, ctrl)
