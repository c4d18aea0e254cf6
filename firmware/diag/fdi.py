"""Model-based fault detection and isolation: the tests behind the plausibility DTCs.

Each tick, after the Kalman filter's correction (``firmware.ecu`` stage 2):

* **Innovation tests** (one per measurement: BA, SWS, WA). The filter's innovation eps_j is
  normalised by its variance under the model, S_jj = (H P H^T)_jj rho + R0_jj + D_j^2 var_F:
  P is the filter's own covariance; rho >= 1 scales it to the road intensity the grade
  estimate measured where the filter's process noise is capped below it; R0 is the sensor
  noise (with ADC quantisation; not the adapted R-hat, which a fault inflates within tens of
  ticks); var_F is the uncertainty of the force taken from the measured current (the screw's
  efficiency applies one way and its inverse the other, so the force lies in a band of width
  |F| (1/eta - eta), uniform: /12; and it changes within the tick: (dF/2)^2). Under the model
  the normalised squares are chi^2(1); their EWMA over W ticks is about chi^2_W / W, and an
  alarm above chi^2_W(1 - alpha) / W has a false-alarm probability alpha per window. The
  statistics hold while the linear model is known not to apply (suspension stroke beyond the
  bump-stop clearance, a measured tyre force near zero or below: lift-off) or the inputs are
  not measurements (an ADC or frame fault: the estimator did not use them), and for
  ``hold_ticks`` afterwards. ``nis_verdicts`` says which tests report (WA's does not: its
  innovation is the road's, whose roughness steps at a segment boundary).
* **Flatline tests** (BA, WA, SWS, current): white noise of std sigma on an ADC of step q gives
  the same count twice with probability at most q / (2 sigma sqrt(pi)); n identical counts in
  a row (away from the rails, which the ADC test owns) then have probability below alpha. A
  stuck sensor is isolated to its channel.
* **Actuator test**: the winding's discrete model over the last tick,
  i_k = a i_{k-1} + b (V_{k-1} - EMF), with the voltage the bridge applied (the commanded duty
  times the measured supply, or the storage voltage when regenerating; an open bridge: no
  current) and the hardware current limit the bridge enforces. The EMF is tracked from the
  current's own response one tick earlier, advanced by K dt times the measured relative
  acceleration (a far better velocity than the estimate); on an outlier it is not re-learnt,
  so a fault that persists keeps its residual. The residual's variance: the current noise
  through the model, and the EMF's advance error from the acceleration's change within a
  tick. A late command (realtime pacing) leaves an older one in force: where the last one
  leaves an outlier, the two before are tried. An EWMA over a few ticks
  (``calib.ecu_params.FDI_ACT_WINDOW``) against its chi-square level; above it for
  ``act_confirm_ticks`` (a supply sample arrives within them: a changed supply explains the
  residual and restarts the test) it fails and holds for ``act_retry_ticks``, then tries
  again. No verdict where the linear model does not hold (bump stops, an airborne tyre), the
  current is not measured, BA or WA looks stuck, or an innovation test fails (the EMF
  advances with BA - WA); the innovation tests pause while it is above its level (their
  force comes from the current). Isolation: the measured current stayed at noise level while
  the model expected current (the statistic's level): an open winding; else the actuator
  does not follow its command (stuck); a current sensor that repeats one count is left to
  its flatline test.
* **Supply voltage** (every sample, 10 ms): below or above the operating range: the two
  supply DTCs and the fault word's supply bit (safety-relevant).

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
T_SUPPLY_LOW, T_SUPPLY_HIGH = 9, 10
N_TESTS = 11
ACT_TESTS = (1 << T_ACT_STUCK) | (1 << T_ACT_OPEN)
OLDER_COMMANDS = 2    # the actuator test also tries the two commands before the last
SUPPLY_TESTS = (1 << T_SUPPLY_LOW) | (1 << T_SUPPLY_HIGH)
FLAT_TESTS = (T_FLAT_BA, T_FLAT_WA, T_FLAT_SWS, T_FLAT_CUR)


@dataclass
class FdiState:
    nis: list = field(default_factory=lambda: [1.0, 1.0, 1.0])  # EWMA per measurement
    flat_last: list = field(default_factory=lambda: [None] * 4)
    flat_run: list = field(default_factory=lambda: [0] * 4)
    invalid_until: int = -1        # the model was invalid: innovation tests wait to this tick
    nis_failed: int = 0            # the innovation tests' last verdict
    force_prev: float = 0.0
    supply_v: float = math.nan     # the last measured supply voltage (NaN: none yet) ...
    supply_failed: int = 0         # ... and the supply tests' verdict on it
    # the actuator test: the last two ticks' measured current and relative acceleration
    # (i1, a1: last tick's) and whether the current was measured, the voltage applied over
    # the last step and the bridge's state, the EMF over the step before (None: unknown),
    # the EWMA, the tick its excursion above the level began (-1: none) and what it saw
    # since, the latched failure
    i1: float = 0.0
    i2: float = 0.0
    a1: float = 0.0
    a2: float = 0.0
    live1: bool = False
    live2: bool = False
    v1: float = 0.0
    v1_dc: float = 0.0
    en1: bool = False
    older: tuple = ()              # the two commands before: (volts, DC volts, enabled)
    emf: float | None = None
    emf_weak: bool = False         # ... learnt while no current flowed
    act: float = 1.0
    act_onset: int = -1
    act_counts: tuple = (0, 0)     # lowest and highest current count since the onset
    act_i_max: float = 0.0         # largest |measured| current since then
    act_latched: int = 0           # the failed actuator test's bit while latched ...
    act_until: int = -1            # ... until this tick (the retry)
    failed: int = 0                # bit per test: failed this tick
    completed: int = 0             # bit per test: ran to a verdict this tick


def step(P: EcuParams, st: FdiState, tick: int, eps, hph, rho: float, force_meas: float,
         counts: tuple, defl: float, lifted: bool, i_meas: float, a_rel: float,
         inputs_valid: bool, supply: int | None = None) -> int:
    """One tick of every test; returns the failed bits (also in ``st.failed``). ``eps``,
    ``hph``: the filter's innovation and diag(H P H^T); ``counts``: this tick's ADC counts of
    BA, WA, SWS, current (None when the ADC had none: no flatline verdict); ``defl``: the
    measured stroke; ``lifted``: the measured tyre force is near zero or below
    (``firmware.akf.airborne``); ``a_rel``: BA - WA; ``inputs_valid``: no ADC or frame fault
    this tick (else the innovation tests hold, as where the model does not apply: the filter
    ran on held values); ``supply``: the supply voltage's counts when a sample arrived this
    tick."""
    settled = tick >= P.fdi.settle_ticks
    if not inputs_valid:
        st.invalid_until = tick + P.fdi.hold_ticks
    f0, c0 = _supply(P, st, settled, supply)
    f2, c2 = _flatline(P, st, settled, counts)
    # The actuator test's EMF advances with BA - WA: no verdict while either repeats its
    # count more often than a healthy one does once in 20 times, or an innovation test is
    # above its level. The innovation tests take their force from the current: they pause
    # while the actuator test is above its level or failed. (Whichever test rises first holds
    # the other: a sensor fault is not blamed on the actuator, nor the actuator's on a sensor.)
    F = P.fdi
    model_ok = (inputs_valid and not lifted and abs(defl) <= F.valid_defl_m
                and st.flat_run[0] < F.act_flat_ticks[0] and st.flat_run[1] < F.act_flat_ticks[1]
                and not st.nis_failed)
    f3, c3 = _actuator(P, st, tick, settled, counts[3], i_meas, a_rel, model_ok)
    if st.act_onset >= 0 or st.act_latched:
        f1, c1 = st.nis_failed, 0
    else:
        f1, c1 = _innovation(P, st, tick, settled, eps, hph, rho, force_meas, defl, lifted)
        st.nis_failed = f1
    st.failed, st.completed = f0 | f1 | f2 | f3, c0 | c1 | c2 | c3
    return st.failed


def _innovation(P, st, tick, settled, eps, hph, rho, force_meas, defl, lifted):
    """The innovation tests: (failed, completed) bits."""
    F, A = P.fdi, P.akf
    failed = completed = 0
    if abs(defl) > F.valid_defl_m or lifted:
        st.invalid_until = tick + F.hold_ticks    # the linear model does not hold here
    dF = force_meas - st.force_prev
    band = abs(force_meas) * F.force_band     # (squares as products: the compiled tick's bits)
    var_f = band * band / 12.0 + 0.25 * dF * dF
    st.force_prev = force_meas
    if tick <= st.invalid_until:                  # the statistics hold meanwhile
        return 0, 0
    lam, clip = F.nis_lambda, F.clip_sq
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


def _supply(P, st, settled, counts):
    """The supply-voltage tests on a new sample: (failed, completed). A sample that differs
    from the last by more than its noise restarts the actuator test (a changed supply, not
    the actuator, explains a residual that began before it was measured)."""
    F = P.fdi
    if counts is None or not 0 < counts < F.supply_full_scale:   # (none, or clipped: the
        return st.supply_failed, 0                               # last verdict holds)
    v = F.supply_offset_v + counts * F.supply_lsb_v
    if not abs(v - st.supply_v) <= F.supply_change_v:            # (NaN: the first sample)
        st.act, st.act_onset, st.emf = 1.0, -1, None
    st.supply_v = v
    if not settled:
        return 0, 0
    st.supply_failed = (1 << T_SUPPLY_LOW if v < F.supply_low_v else 0) | (
        1 << T_SUPPLY_HIGH if v > F.supply_high_v else 0)
    return st.supply_failed, SUPPLY_TESTS


def _bus_voltage(P, st, regen: bool) -> float:
    """The DC voltage behind the bridge: the storage element's, or the measured supply
    (the vehicle's nominal bus voltage until a sample arrived)."""
    if regen:
        return P.plant.storage_voltage
    return P.plant.bus_voltage if math.isnan(st.supply_v) else st.supply_v


def _actuator(P, st, tick, settled, count, i_meas, a_rel, model_ok):
    """The actuator test over the step that ended now: (failed, completed)."""
    F, ap = P.fdi, P.actuator
    a, b, kdt = ap.current_a, ap.current_b, P.plant.force_constant * P.dt_s
    live = count is not None and 0 < count < P.adc.motor_current.full_scale
    # The bridge applied the last command, or, where it came late (realtime pacing: the
    # plant steps on its clock with the latest valid one, and holds one for up to three
    # ticks), an older one: where the last leaves an outlier, the two before are tried. A
    # stuck duty or an open winding is none of them.
    verdict, v, limited, emf, used = False, math.inf, False, None, None
    if live and st.live1:
        emf_adv = None
        if st.emf is not None and st.live2:
            emf_adv = st.emf + kdt * 0.25 * (st.a2 + 2.0 * st.a1 + a_rel)
        da = max(abs(a_rel - st.a1), abs(st.a1 - st.a2))
        for volt, v_dc, enabled in ((st.v1, st.v1_dc, st.en1), *st.older):
            if not enabled:                  # the bridge was open: no current
                ip, lim, var = 0.0, False, F.cur_sigma_a ** 2
            elif emf_adv is not None:
                ip, lim = _winding(P, st.i1, volt, emf_adv, v_dc)
                adv = 0.5 * b * kdt * da
                var = F.act_var + adv * adv
            else:
                continue
            r = i_meas - ip
            if r * r / var < v:
                verdict, v, limited, used = True, r * r / var, lim, (volt, enabled)
            if v <= F.clip_sq:
                break
        emf = emf_adv
    # the EMF over the step that ended: from the current's response where it follows the
    # model, else (an outlier, the current limit acting or, unpredicted, the current ending
    # at it: the bridge lowered its voltage) the advanced estimate, not re-learnt. An EMF
    # learnt while no current flowed is weak (an open winding shows the applied voltage as
    # its EMF): where current then starts to flow against it (a winding conducting again),
    # the outlier is learnt from, not judged. It advances too while this test's failure holds
    # the bridge open: learnt again after the retry, it took a stuck duty's voltage for EMF.
    at_limit = limited or abs(i_meas) >= P.plant.current_limit - 5.0 * F.cur_sigma_a
    if used is not None:                     # (the open bridge's: no EMF to see)
        volt = used[0] if used[1] else None
    else:
        volt = st.v1 if st.en1 else None
    quiet = F.open_ratio * F.cur_sigma_a
    outlier = verdict and v > F.clip_sq
    if outlier and st.emf_weak and abs(i_meas) >= quiet:
        verdict = outlier = False
    if volt is not None and live and st.live1 and not (at_limit or outlier):
        st.emf = volt - (i_meas - a * st.i1) / b
        st.emf_weak = abs(i_meas) < quiet and abs(st.i1) < quiet
    elif live and st.live1 and (volt is not None or (st.act_latched and model_ok)):
        st.emf = emf                         # (None where there was none to advance)
    else:
        st.emf = None
    st.i2, st.i1, st.a2, st.a1 = st.i1, i_meas, st.a1, a_rel
    st.live2, st.live1 = st.live1, live
    if st.act_latched:                       # a failure holds until the retry
        if tick < st.act_until:
            return st.act_latched, st.act_latched
        st.act_latched, st.act, st.act_onset = 0, 1.0, -1
    if not (verdict and model_ok and math.isfinite(v)):
        return 0, 0
    st.act += F.act_lambda * (min(v, F.clip_sq) - st.act)
    if not (settled and F.actuator_verdicts):
        return 0, 0
    if st.act <= F.act_threshold:
        st.act_onset = -1
        return 0, ACT_TESTS
    if st.act_onset < 0:
        st.act_onset, st.act_counts, st.act_i_max = tick, (count, count), 0.0
    lo, hi = st.act_counts
    st.act_counts = (min(lo, count), max(hi, count))
    st.act_i_max = max(st.act_i_max, abs(i_meas))
    if tick - st.act_onset < F.act_confirm_ticks or st.act_counts[0] == st.act_counts[1]:
        return 0, 0           # (not yet; a current sensor that repeats one count: its flatline)
    sig = F.cur_sigma_a
    opened = st.act_i_max < F.open_ratio * sig    # (the model expected current: the level)
    st.act_latched = 1 << (T_ACT_OPEN if opened else T_ACT_STUCK)
    st.act_until = tick + F.act_retry_ticks
    return st.act_latched, ACT_TESTS


def _winding(P, i1: float, volt: float, emf: float, v_dc: float) -> tuple[float, bool]:
    """The current one tick after ``i1`` at ``volt`` against ``emf``, and whether the
    bridge's hardware current limit acted (it lowers the voltage it applies, within +-v_dc,
    so that the current ends at the limit)."""
    ap, lim = P.actuator, P.plant.current_limit
    i = ap.current_a * i1 + ap.current_b * (volt - emf)
    if abs(i) <= lim:
        return i, False
    v = (math.copysign(lim, i) - ap.current_a * i1) / ap.current_b + emf
    v = min(v_dc, max(-v_dc, v))
    return ap.current_a * i1 + ap.current_b * (v - emf), True


def command(P: EcuParams, st: FdiState, duty_q15: int, enable: bool, regen: bool) -> None:
    """The tick's command: the voltage the bridge applies over the next step (and the ones
    before, which a late command leaves in force)."""
    st.older = ((st.v1, st.v1_dc, st.en1), *st.older[:OLDER_COMMANDS - 1])
    st.en1 = enable
    st.v1_dc = _bus_voltage(P, st, regen)
    st.v1 = duty_q15 / 32768.0 * st.v1_dc if enable else 0.0


def _full_scale(P: EcuParams, c: int) -> int:
    return (P.adc.body_accel, P.adc.wheel_accel, P.adc.susp_defl, P.adc.motor_current)[c].full_scale
