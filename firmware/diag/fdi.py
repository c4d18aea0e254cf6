"""Model-based fault detection and isolation: the tests behind the plausibility DTCs.

Each tick, after the Kalman filter's correction (``firmware.ecu`` stage 2):

* **Innovation tests** (one per measurement: BA, SWS, WA). The filter's innovation eps_j is
  normalised by its variance under the model, S_jj = (H P H^T)_jj rho + R0_jj + D_j^2 var_F:
  P is the filter's own covariance; rho >= 1 scales it to the road intensity the grade
  estimate measured where the filter's process noise is capped below it; R0 is the sensor
  noise (with ADC quantisation; not the adapted R-hat, which a fault or a sensor loss
  inflates for seconds); var_F is the uncertainty of the force taken from the measured current (the screw's
  efficiency applies one way and its inverse the other, so the force lies in a band of width
  |F| (1/eta - eta), uniform: /12; and it changes within the tick: (dF/2)^2). Under the model
  the normalised squares are chi^2(1); their EWMA over W ticks is about chi^2_W / W, and an
  alarm above chi^2_W(1 - alpha) / W has a false-alarm probability alpha per window. The
  statistics hold while the linear model is known not to apply (suspension stroke beyond the
  bump-stop clearance, tyre deflection beyond the static one: lift-off) or the inputs are
  not measurements (an ADC or frame fault: the filter ran on held values), and for
  ``hold_ticks`` afterwards. ``nis_verdicts`` says which tests report (WA's does not: its
  innovation is the road's, whose roughness steps at a segment boundary).
* **Flatline tests** (BA, WA, SWS, current): white noise of std sigma on an ADC of step q gives
  the same count twice with probability at most q / (2 sigma sqrt(pi)); n identical counts in
  a row (away from the rails, which the ADC test owns) then have probability below alpha. A
  stuck sensor is isolated to its channel.
* **Actuator test**: the winding model i_k = a i_{k-1} + b (V_{k-1} - EMF) with the voltage
  the bridge applied last tick (its duty and DC voltage; an open bridge: no current) and the
  EMF from the estimated relative velocity and the measured relative acceleration (no verdict
  where the bridge's hardware current limit acts: it lowers the applied voltage). The
  residual is normalised by its variance (current noise through the model, and the velocity
  estimate's variance from P); an EWMA over a short window against its chi^2 level. A
  residual with the measured current at noise level while the model expects current is an
  open winding; otherwise the actuator does not follow its command (stuck duty); with the
  current sensor flat it is the sensor.

Isolation: a flatline names its channel; the actuator test names the actuator (or the current
sensor); an innovation alarm names the measurement whose test fired, which is the faulty one
only for the channels whose fault does not reach the others' innovations first (see
docs/diagnostics.md for the measured signatures): the DTC says "plausibility" and the channel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from firmware.params import EcuParams

# test indices (the DTC table in firmware.diag.dtc names them)
T_NIS_BA, T_NIS_SWS, T_NIS_WA = 0, 1, 2
T_FLAT_BA, T_FLAT_WA, T_FLAT_SWS, T_FLAT_CUR = 3, 4, 5, 6
T_ACT_STUCK, T_ACT_OPEN = 7, 8
N_TESTS = 9
FLAT_TESTS = (T_FLAT_BA, T_FLAT_WA, T_FLAT_SWS, T_FLAT_CUR)


@dataclass
class FdiState:
    nis: list = field(default_factory=lambda: [1.0, 1.0, 1.0])  # EWMA per measurement
    cur: float = 1.0               # EWMA of the current residual's normalised square
    flat_last: list = field(default_factory=lambda: [None] * 4)
    flat_run: list = field(default_factory=lambda: [0] * 4)
    invalid_until: int = -1        # the model was invalid: innovation tests wait to this tick
    force_prev: float = 0.0
    i_prev: float = 0.0
    duty_prev: int = 0             # last tick's command (what the bridge applied since)
    enable_prev: bool = False
    regen_prev: bool = False
    failed: int = 0                # bit per test: failed this tick
    completed: int = 0             # bit per test: ran to a verdict this tick


def step(P: EcuParams, st: FdiState, tick: int, eps, hph, rho: float, force_meas: float,
         counts: tuple, defl: float, dtd_est: float, i_meas: float, v_rel: float,
         var_v_rel: float, a_rel: float, inputs_valid: bool) -> int:
    """One tick of every test; returns the failed bits (also in ``st.failed``). ``eps``,
    ``hph``: the filter's innovation and diag(H P H^T); ``counts``: this tick's ADC counts of
    BA, WA, SWS, current (None when the ADC had none: no flatline verdict); ``defl``: the
    measured stroke; ``dtd_est``: the estimated tyre deflection; ``v_rel``, ``var_v_rel``:
    the estimated relative velocity and its variance; ``a_rel``: BA - WA; ``inputs_valid``:
    no ADC or frame fault this tick (else the innovation tests hold, as where the model does
    not apply: the filter ran on held values)."""
    settled = tick >= P.fdi.settle_ticks
    if not inputs_valid:
        st.invalid_until = tick + P.fdi.hold_ticks
    f1, c1 = _innovation(P, st, tick, settled, eps, hph, rho, force_meas, defl, dtd_est)
    f2, c2 = _flatline(P, st, settled, counts)
    f3, c3 = _actuator(P, st, settled, counts[3] is not None, i_meas, v_rel, var_v_rel, a_rel,
                       bool(f2 & 1 << T_FLAT_CUR))
    st.failed, st.completed = f1 | f2 | f3, c1 | c2 | c3
    return st.failed


def _innovation(P, st, tick, settled, eps, hph, rho, force_meas, defl, dtd_est):
    """The innovation tests: (failed, completed) bits."""
    F, A = P.fdi, P.akf
    failed = completed = 0
    if abs(defl) > F.valid_defl_m or abs(dtd_est) > F.valid_tyre_m:
        st.invalid_until = tick + F.hold_ticks    # the linear model does not hold here
    dF = force_meas - st.force_prev
    var_f = (abs(force_meas) * F.force_band) ** 2 / 12.0 + 0.25 * dF * dF
    st.force_prev = force_meas
    if tick <= st.invalid_until:                  # the statistics hold meanwhile
        return 0, 0
    lam, clip = F.nis_lambda, F.clip
    for j in range(len(eps)):
        d = A.D.item(j)
        s = hph[j] * rho + A.r0.item(j, j) + d * d * var_f
        v = eps[j] * eps[j] / s
        if not math.isfinite(v):
            continue                              # (a diverged filter is its own fault)
        st.nis[j] += lam * (min(v, clip) - st.nis[j])
        if settled and F.nis_verdicts[j]:
            completed |= 1 << j
            if st.nis[j] > F.nis_threshold:
                failed |= 1 << j
    return failed, completed


def _flatline(P, st, settled, counts):
    """The flatline tests: (failed, completed) bits."""
    failed = completed = 0
    for c, t in enumerate(FLAT_TESTS):
        n = P.fdi.flat_ticks[c]
        cnt = counts[c]
        if not n or cnt is None:
            continue
        if cnt == st.flat_last[c] and 0 < cnt < _full_scale(P, c):   # (rails: the ADC's)
            st.flat_run[c] += 1
        else:
            st.flat_run[c] = 1
            st.flat_last[c] = cnt
        if settled:
            completed |= 1 << t
            if st.flat_run[c] >= n:
                failed |= 1 << t
    return failed, completed


def _actuator(P, st, settled, sampled, i_meas, v_rel, var_v_rel, a_rel, sensor_flat):
    """The actuator test on the winding model over the last tick: (failed, completed)."""
    F, ap, plant = P.fdi, P.actuator, P.plant
    failed = completed = 0
    if st.enable_prev:
        v_dc = plant.storage_voltage if st.regen_prev else plant.bus_voltage
        volt = st.duty_prev / 32768.0 * v_dc
        emf = plant.force_constant * (v_rel - 0.5 * P.dt_s * a_rel)
        i_pred = ap.current_a * st.i_prev + ap.current_b * (volt - emf)
        var_r = F.cur_sigma_a ** 2 * (1.0 + ap.current_a ** 2) + (
            ap.current_b * plant.force_constant) ** 2 * var_v_rel
    else:
        i_pred = 0.0                      # an open bridge carries no current
        var_r = F.cur_sigma_a ** 2
    r = i_meas - i_pred
    v = r * r / var_r
    st.i_prev = i_meas
    # the bridge's hardware current limit lowers the voltage it applies: no verdict there
    limited = max(abs(i_pred), abs(i_meas)) >= plant.current_limit - 5.0 * F.cur_sigma_a
    if not (math.isfinite(v) and sampled) or limited:
        return 0, 0
    st.cur += F.cur_lambda * (min(v, F.clip) - st.cur)
    if settled and F.actuator_verdicts:
        completed = (1 << T_ACT_STUCK) | (1 << T_ACT_OPEN)
        if st.cur > F.cur_threshold and not sensor_flat:
            sig = F.cur_sigma_a
            if abs(i_meas) < F.open_ratio * sig and abs(i_pred) > 10 * F.open_ratio * sig:
                failed = 1 << T_ACT_OPEN
            else:
                failed = 1 << T_ACT_STUCK
    return failed, completed


def command(st: FdiState, duty_q15: int, enable: bool, regen: bool) -> None:
    """The tick's command, for the actuator test of the next tick."""
    st.duty_prev, st.enable_prev, st.regen_prev = duty_q15, enable, regen


def _full_scale(P: EcuParams, c: int) -> int:
    return (P.adc.body_accel, P.adc.wheel_accel, P.adc.susp_defl, P.adc.motor_current)[c].full_scale
