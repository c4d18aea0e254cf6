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
  advances with BA - WA; so none either while WA's innovation statistic, which gives no
  verdict of its own, is above its level); the innovation tests pause while it is above
  its level (their force comes from the current). Isolation: the measured current stayed at noise level while
  the model expected current (the statistic's level): an open winding; else the actuator
  does not follow its command (stuck); a current sensor that repeats one count is left to
  its flatline test.
* **Supply voltage** (every sample, 10 ms): below or above the operating range: the two
  supply DTCs and the fault word's supply bit (safety-relevant).

Isolation: a flatline names its channel; the actuator test names the actuator (or the current
sensor); an innovation alarm names the measurement whose test fired, which is the faulty one
only for the channels whose fault does not reach the others' innovations first (see
docs/diagnostics.md for the measured signatures): the DTC says "plausibility" and the channel.

Compiled (numba) over the state record's ``fdi`` fields. Python's ``None`` is a flag there:
``emf_known`` (the EMF over the step before is known), ``counts`` of -1 (no good sample), the
commands before the last in a ring of ``OLDER_COMMANDS`` (``n_older`` of them, the newest
first).
"""

from __future__ import annotations

import math

import numpy as np

from firmware import adc
from firmware.kernels import njit
from firmware.util import clamp, pymax, pymin

# test indices (the DTC table in firmware.diag.dtc names them)
T_NIS_BA, T_NIS_SWS, T_NIS_WA = 0, 1, 2
T_FLAT_BA, T_FLAT_WA, T_FLAT_SWS, T_FLAT_CUR = 3, 4, 5, 6
T_ACT_STUCK, T_ACT_OPEN = 7, 8
T_SUPPLY_LOW, T_SUPPLY_HIGH = 9, 10
# the isolation bank's decisions (firmware.diag.bank): a sensor named, or none
T_ISO_BA, T_ISO_WA, T_ISO_SWS, T_ISO_CUR, T_NOT_ISOLATED = 11, 12, 13, 14, 15
# ... and the actuator named through them (the actuator test detects; a BA or WA fault that
# fooled it is named by the bank instead)
T_NAME_ACT_STUCK, T_NAME_ACT_OPEN = 16, 17
N_TESTS = 18
NIS_TESTS = (1 << T_NIS_BA) | (1 << T_NIS_SWS) | (1 << T_NIS_WA)
ACT_TESTS = (1 << T_ACT_STUCK) | (1 << T_ACT_OPEN)
OLDER_COMMANDS = 2    # the actuator test also tries the two commands before the last
SUPPLY_TESTS = (1 << T_SUPPLY_LOW) | (1 << T_SUPPLY_HIGH)
FLAT_TESTS = (T_FLAT_BA, T_FLAT_WA, T_FLAT_SWS, T_FLAT_CUR)

STATE = np.dtype([
    ("nis", "f8", (3,)),              # EWMA per measurement
    ("flat_last", "i8", (4,)), ("flat_run", "i8", (4,)),
    ("invalid_until", "i8"),          # the model was invalid: innovation tests wait to here
    ("nis_failed", "i8"),             # the innovation tests' last verdict
    ("force_prev", "f8"),
    ("supply_v", "f8"),               # the last measured supply voltage (NaN: none yet) ...
    ("supply_failed", "i8"),          # ... and the supply tests' verdict on it
    # the actuator test (firmware.diag.fdi.FdiState says what each is)
    ("i1", "f8"), ("i2", "f8"), ("a1", "f8"), ("a2", "f8"), ("live1", "u1"), ("live2", "u1"),
    ("v1", "f8"), ("v1_dc", "f8"), ("en1", "u1"),
    ("older_v", "f8", (OLDER_COMMANDS,)), ("older_dc", "f8", (OLDER_COMMANDS,)),
    ("older_en", "u1", (OLDER_COMMANDS,)), ("n_older", "i8"),
    ("emf", "f8"), ("emf_known", "u1"), ("emf_weak", "u1"),
    ("act", "f8"), ("act_onset", "i8"), ("act_lo", "i8"), ("act_hi", "i8"),
    ("act_i_max", "f8"), ("act_latched", "i8"), ("act_until", "i8"),
    ("failed", "i8"),                 # bit per test: failed this tick
    ("completed", "i8"),              # bit per test: ran to a verdict this tick
])


def init(S) -> None:
    S.nis[:] = 1.0
    S.flat_last[:] = -1
    S.invalid_until = -1
    S.supply_v = math.nan
    S.act = 1.0
    S.act_onset = -1
    S.act_until = -1


@njit
def step(P, S, tick: int, eps, hph, rho: float, force_meas: float, counts, defl: float,
         lifted: bool, i_meas: float, a_rel: float, inputs_valid: bool, supply: int,
         a_rel_measured: bool = True) -> int:
    """One tick of every test (``firmware.diag.fdi.step``); returns the failed bits.
    ``counts``: this tick's good counts of BA, WA, SWS, current (-1: none); ``supply``: the
    supply voltage's counts when a sample arrived this tick (-1: none);
    ``a_rel_measured``: ``a_rel`` is BA - WA as measured (else, with either sensor out,
    ``firmware.diag.degrade``, the actuator test gives no verdict)."""
    F = P.fdi
    settled = tick >= F.settle_ticks
    if not inputs_valid:
        S.invalid_until = tick + F.hold_ticks
    f0, c0 = _supply(F, S, settled, supply)
    f2, c2 = _flatline(P, S, settled, counts)
    model_ok = (inputs_valid and a_rel_measured and not lifted and abs(defl) <= F.valid_defl_m
                and S.flat_run[0] < F.act_flat_ticks[0] and S.flat_run[1] < F.act_flat_ticks[1]
                and not S.nis_failed and S.nis[T_NIS_WA] <= F.nis_threshold)
    f3, c3 = _actuator(P, S, tick, settled, counts[3], i_meas, a_rel, model_ok)
    if S.act_onset >= 0 or S.act_latched:
        f1, c1 = S.nis_failed, 0
    else:
        f1, c1 = _innovation(P, S, tick, settled, eps, hph, rho, force_meas, defl, lifted)
        S.nis_failed = f1
    S.failed, S.completed = f0 | f1 | f2 | f3, c0 | c1 | c2 | c3
    return S.failed


@njit
def _innovation(P, S, tick, settled, eps, hph, rho, force_meas, defl, lifted):
    F, A = P.fdi, P.akf
    failed = completed = 0
    if abs(defl) > F.valid_defl_m or lifted:
        S.invalid_until = tick + F.hold_ticks    # the linear model does not hold here
    dF = force_meas - S.force_prev
    band = abs(force_meas) * F.force_band
    var_f = band * band / 12.0 + 0.25 * dF * dF
    S.force_prev = force_meas
    if tick <= S.invalid_until:                  # the statistics hold meanwhile
        return 0, 0
    lam, clip = F.nis_lambda, F.clip_sq
    for j in range(eps.shape[0]):
        d = A.D[j]
        s = hph[j] * rho + A.r0[j, j] + d * d * var_f
        v = eps[j] * eps[j] / s
        if not math.isfinite(v):
            continue                             # (a diverged filter is its own fault)
        S.nis[j] += lam * (pymin(v, clip) - S.nis[j])
        if settled and F.nis_verdicts[j]:
            completed |= 1 << j
            if S.nis[j] > F.nis_threshold:
                failed |= 1 << j
    return failed, completed


@njit
def _flatline(P, S, settled, counts):
    failed = completed = 0
    for c in range(4):
        t = FLAT_TESTS[c]
        n = P.fdi.flat_ticks[c]
        cnt = counts[c]
        if not n or cnt < 0:
            continue
        if cnt == S.flat_last[c] and 0 < cnt < P.adc.full_scale[c]:   # (rails: the ADC's)
            S.flat_run[c] += 1
        else:
            S.flat_run[c] = 1
            S.flat_last[c] = cnt
        if settled:
            completed |= 1 << t
            if S.flat_run[c] >= n:
                failed |= 1 << t
    return failed, completed


@njit
def _supply(F, S, settled, counts):
    if not 0 < counts < F.supply_full_scale:           # (none, or clipped: the last
        return S.supply_failed, 0                      # verdict holds)
    v = F.supply_offset_v + counts * F.supply_lsb_v
    if not abs(v - S.supply_v) <= F.supply_change_v:   # (NaN: the first sample)
        S.act, S.act_onset, S.emf_known = 1.0, -1, False
    S.supply_v = v
    if not settled:
        return 0, 0
    S.supply_failed = ((1 << T_SUPPLY_LOW) if v < F.supply_low_v else 0) | (
        (1 << T_SUPPLY_HIGH) if v > F.supply_high_v else 0)
    return S.supply_failed, SUPPLY_TESTS


@njit
def bus_voltage(P, S, regen: bool) -> float:
    """The DC voltage behind the bridge: the storage element's, or the measured supply (the
    nominal bus voltage until a sample arrived)."""
    if regen:
        return P.plant.storage_voltage
    return P.plant.bus_voltage if math.isnan(S.supply_v) else S.supply_v


@njit
def _winding(P, i1: float, volt: float, emf: float, v_dc: float):
    """The current one tick after ``i1`` at ``volt`` against ``emf``, and whether the
    bridge's hardware current limit acted."""
    ap, lim = P.actuator, P.plant.current_limit
    i = ap.current_a * i1 + ap.current_b * (volt - emf)
    if abs(i) <= lim:
        return i, False
    v = (math.copysign(lim, i) - ap.current_a * i1) / ap.current_b + emf
    v = clamp(v, -v_dc, v_dc)
    return ap.current_a * i1 + ap.current_b * (v - emf), True


@njit
def _actuator(P, S, tick, settled, count, i_meas, a_rel, model_ok):
    """The actuator test over the step that ended now: (failed, completed)."""
    F, ap = P.fdi, P.actuator
    a, b, kdt = ap.current_a, ap.current_b, P.plant.force_constant * P.dt_s
    live = 0 < count < P.adc.full_scale[adc.CUR]
    verdict, v, limited = False, math.inf, False
    emf, emf_ok = 0.0, False
    used, used_volt, used_en = False, 0.0, False
    if live and S.live1:
        emf_adv, adv_ok = 0.0, False
        if S.emf_known and S.live2:
            emf_adv, adv_ok = S.emf + kdt * 0.25 * (S.a2 + 2.0 * S.a1 + a_rel), True
        da = pymax(abs(a_rel - S.a1), abs(S.a1 - S.a2))
        for k in range(1 + S.n_older):      # the last command, then the ones before
            if k == 0:
                volt, v_dc, enabled = S.v1, S.v1_dc, bool(S.en1)
            else:
                volt, v_dc, enabled = S.older_v[k - 1], S.older_dc[k - 1], bool(S.older_en[k - 1])
            if not enabled:                  # the bridge was open: no current
                ip, lim, var = 0.0, False, F.cur_var
            elif adv_ok:
                ip, lim = _winding(P, S.i1, volt, emf_adv, v_dc)
                adv = 0.5 * b * kdt * da
                var = F.act_var + adv * adv
            else:
                continue
            r = i_meas - ip
            if r * r / var < v:
                verdict, v, limited = True, r * r / var, lim
                used, used_volt, used_en = True, volt, enabled
            if v <= F.clip_sq:
                break
        emf, emf_ok = emf_adv, adv_ok
    # the EMF over the step that ended (firmware.diag.fdi._actuator says when it is learnt)
    at_limit = limited or abs(i_meas) >= P.plant.current_limit - 5.0 * F.cur_sigma_a
    if used:                                 # (the open bridge's: no EMF to see)
        volt_ok, volt = used_en, used_volt
    else:
        volt_ok, volt = bool(S.en1), S.v1
    quiet = F.open_ratio * F.cur_sigma_a
    outlier = verdict and v > F.clip_sq
    if outlier and S.emf_weak and abs(i_meas) >= quiet:
        verdict = outlier = False
    if volt_ok and live and S.live1 and not (at_limit or outlier):
        S.emf, S.emf_known = volt - (i_meas - a * S.i1) / b, True
        S.emf_weak = abs(i_meas) < quiet and abs(S.i1) < quiet
    elif live and S.live1 and (volt_ok or (S.act_latched and model_ok)):
        S.emf, S.emf_known = emf, emf_ok      # (none where there was none to advance)
    else:
        S.emf_known = False
    S.i2, S.i1, S.a2, S.a1 = S.i1, i_meas, S.a1, a_rel
    S.live2, S.live1 = S.live1, live
    if S.act_latched:                        # a failure holds until the retry
        if tick < S.act_until:
            return S.act_latched, S.act_latched
        S.act_latched, S.act, S.act_onset = 0, 1.0, -1
    if not (verdict and model_ok and math.isfinite(v)):
        return 0, 0
    S.act += F.act_lambda * (pymin(v, F.clip_sq) - S.act)
    if not (settled and F.actuator_verdicts):
        return 0, 0
    if S.act <= F.act_threshold:
        S.act_onset = -1
        return 0, ACT_TESTS
    if S.act_onset < 0:
        S.act_onset, S.act_lo, S.act_hi, S.act_i_max = tick, count, count, 0.0
    S.act_lo, S.act_hi = pymin(S.act_lo, count), pymax(S.act_hi, count)
    S.act_i_max = pymax(S.act_i_max, abs(i_meas))
    if tick - S.act_onset < F.act_confirm_ticks or S.act_lo == S.act_hi:
        return 0, 0           # (not yet; a current sensor that repeats one count: its flatline)
    opened = S.act_i_max < F.open_ratio * F.cur_sigma_a
    S.act_latched = 1 << (T_ACT_OPEN if opened else T_ACT_STUCK)
    S.act_until = tick + F.act_retry_ticks
    return S.act_latched, ACT_TESTS


@njit
def command(P, S, duty_q15: int, enable: bool, regen: bool) -> None:
    """The tick's command: the voltage the bridge applies over the next step (and the ones
    before, which a late command leaves in force)."""
    for k in range(OLDER_COMMANDS - 1, 0, -1):
        S.older_v[k], S.older_dc[k], S.older_en[k] = (S.older_v[k - 1], S.older_dc[k - 1],
                                                      S.older_en[k - 1])
    S.older_v[0], S.older_dc[0], S.older_en[0] = S.v1, S.v1_dc, S.en1
    S.n_older = min(OLDER_COMMANDS, S.n_older + 1)
    S.en1 = enable
    S.v1_dc = bus_voltage(P, S, regen)
    S.v1 = duty_q15 / 32768.0 * S.v1_dc if enable else 0.0
