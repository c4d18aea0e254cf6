"""Isolation after detection: the bank of residual generators and its decision
(docs/isolation.md).

Four fixed-gain filters on the winding model (``calib.fdi_bank``), filter k blind to sensor
k (``BLIND``: BA, WA, SWS, current), each predicting with the voltage the bridge applied over
the last step (an open bridge: no current, the current state held at zero) and correcting
with the three channels it reads (the bridge open: the car's five states alone, with the gain
and covariances of that model). Its whitened innovation nu' S^-1 nu / 3, S = q S_road +
S_noise + var_F S_force exact for the fixed gain at the road intensity q the grade estimate
gives (no Riccati step), goes through an EWMA against chi2_{3W}(1 - alpha) / (3W): above it
the filter is inconsistent. The statistics hold, as the innovation tests' do, while the
model does not apply or a channel a filter reads is held (no correction then either).

The decision (an episode): a detection (an innovation test, a flatline test or the actuator
test failed) opens one. A fault of sensor j cannot make the filter blind to j inconsistent,
so every filter found inconsistent during the episode clears the sensor it is blind to.
* a flatline test fails: that channel, named by its own DTC;
* the actuator test failed: it advances the back-EMF with BA - WA, so a fault of either can
  fool it; a BA or WA fault the bank names is named instead, else the actuator (stuck, or
  open where the test found no current) once BA, WA and the current are cleared (the
  current-blind filter found the force wrong, which no current sensor's fault does), or
  after ``act_ticks`` where the bank cleared nothing or the current, unless the current's
  reading was held or clipped in the episode; the current left alone (the current sensor or
  the actuator), a partial picture or a clipped current: not isolated;
* three sensors cleared and the fourth's filter consistent for ``confirm_ticks``: that
  sensor (``T_ISO_*``);
* all four cleared (no single sensor fits), ``decide_ticks`` without a decision, or the
  evidence ended (no test failing and no filter above its level for ``settle_ticks``: a
  fault that went away leaves no more to learn): not isolated (``T_NOT_ISOLATED``), the
  sensors left in ``candidates`` (state only, so far).
An episode's decision is reported once (a failed report of its test); the next episode opens
once detection has been quiet for ``settle_ticks`` (1 s) after it.

The bank's arithmetic is float in both arithmetic paths (as the innovation tests':
``firmware.diag.fdi``); compiled (numba) over the state record's ``bank`` fields.
"""

from __future__ import annotations

import math

import numpy as np

from firmware import adc
from firmware.diag import fdi
from firmware.kernels import njit
from firmware.util import pymin

N_FILTERS, N_READS, N_STATES = 4, 3, 7
BLIND = ("ba", "wa", "defl", "current")  # filter k is blind to BLIND[k] (calib.fdi_bank.SENSORS)
CURRENT_STATE = 5                        # the winding current in the filters' state
# decisions (``S.decided``)
NONE, ISOLATED_BA, ISOLATED_WA, ISOLATED_SWS, ISOLATED_CUR, NOT_ISOLATED, BY_TEST = \
    -1, 0, 1, 2, 3, 4, 5
ACTUATOR_STUCK, ACTUATOR_OPEN = 6, 7     # the actuator test's conclusion stands
ACT_STUCK_BIT, ACT_OPEN_BIT = 1, 2       # (``act``: which the actuator test found)
SENSOR_BA, SENSOR_WA = 1 << 0, 1 << 1    # (the cleared bits of the actuator test's inputs)
SENSOR_CUR = 1 << 3                      # (cleared: the current-blind filter saw the force)

STATE = np.dtype([
    ("x", "f8", (N_FILTERS, N_STATES)),
    ("stat", "f8", (N_FILTERS,)),
    ("above", "i8"),                     # bit k: filter k's statistic above its level now
    ("invalid_until", "i8"),             # the statistics hold to here
    ("episode", "i8"),                   # tick the episode opened (-1: none)
    ("cleared", "i8"),                   # bit k: sensor k cleared in this episode
    ("alone_since", "i8"),               # tick one sensor was left alone (-1: not so)
    ("decided", "i8"),                   # the episode's decision (NONE while open)
    ("quiet_since", "i8"),               # tick detection (and the filters) went quiet
    ("candidates", "i8"),                # the last decision's sensors left (bits)
    ("nu", "f8", (N_READS,)), ("Sm", "f8", (N_READS, N_READS)),   # (scratch: the tick
    ("xp", "f8", (N_STATES,)),                                    #  allocates nothing)
    ("z", "f8", (4,)),                   # the tick's channels [BA, SWS, WA, current]
    ("snapshot", "i8", (7,)),            # the freeze frame at the episode's detection
    ("reported", "u1"),                  # a decision was reported this tick
    ("act", "i8"),                       # the actuator test's findings in this episode ...
    ("act_since", "i8"),                 # ... since this tick
    ("cur_held", "u1"),                  # the current's reading held or clipped in it
])


def init(S) -> None:
    S.stat[:] = 1.0
    S.invalid_until = S.episode = S.alone_since = S.quiet_since = -1
    S.decided = NONE


@njit
def _inv3_quad(S, nu) -> float:
    """nu' S^-1 nu for a symmetric 3 x 3 S (the adjugate); inf where S is not positive."""
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    d, e, f = S[1, 1], S[1, 2], S[2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A + b * B + c * C
    if not det > 0.0:
        return math.inf
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    x, y, z = nu[0], nu[1], nu[2]
    q = (A * x * x + D * y * y + F * z * z + 2.0 * (B * x * y + C * x * z + E * y * z))
    return q / det


@njit
def filters(P, S, tick: int, z, held: int, volt: float, enabled: bool, intensity: float,
            var_f: float, model_ok: bool, settled: bool) -> None:
    """One tick of the four filters: ``z`` the channels [BA, SWS, WA, current] (SI),
    ``held`` their bits whose value is not this tick's, ``volt`` the voltage over the step
    that ended, ``enabled`` whether the bridge was closed over it."""
    B = P.bank
    if not model_ok:
        S.invalid_until = tick + P.fdi.hold_ticks
    x, nu, Sm, xp = S.x, S.nu, S.Sm, S.xp
    above = 0
    pl = P.plant
    for k in range(N_FILTERS):
        # the screw's efficiency: the model's force is K_f i; the corner's is eta K_f i or
        # K_f i / eta by the direction of the power flow, which the filter's own estimate
        # tells (its current and relative velocity: no sensor it is blind to): the
        # difference is a known force over the step and in the accelerations read
        i_est, rel = x[k, CURRENT_STATE], x[k, 0] - x[k, 1]
        g = pl.efficiency if i_est * rel >= 0.0 else 1.0 / pl.efficiency
        f_corr = (g - 1.0) * pl.force_constant * i_est if enabled else 0.0
        # predict: x = phi x + gamma volt (an open bridge carries no current)
        phi = B.phi[k] if enabled else B.phi_open[k]
        for i in range(N_STATES):
            s = (B.gamma[k, i] * volt if enabled else 0.0) + B.gamma_force[k, i] * f_corr
            for j in range(N_STATES):
                s += phi[i, j] * x[k, j]
            xp[i] = s
        for i in range(N_STATES):
            x[k, i] = xp[i]
        if not enabled:
            x[k, CURRENT_STATE] = 0.0
        skip = False
        for r in range(N_READS):
            c = B.reads[k * N_READS + r]
            if (held >> c) & 1:
                skip = True
            s = z[c] - B.D_force[k, r] * f_corr
            for j in range(N_STATES):
                s -= B.H[k, r, j] * x[k, j]
            nu[r] = s
        if skip:                             # (a channel it reads is an old value)
            S.invalid_until = max(S.invalid_until, tick + P.fdi.hold_ticks)
            continue
        # the gain and covariance of the bridge's state over the step (``K_open``: the
        # car's five states alone, the winding's rows zero)
        s_road = B.S_road[k] if enabled else B.S_road_open[k]
        s_noise = B.S_noise[k] if enabled else B.S_noise_open[k]
        gain = B.K[k] if enabled else B.K_open[k]
        for r in range(N_READS):
            for j in range(N_READS):
                Sm[r, j] = (intensity * s_road[r, j] + s_noise[r, j]
                            + var_f * B.S_force[k, r, j])
        d2 = _inv3_quad(Sm, nu) / N_READS
        for i in range(N_STATES):
            s = 0.0
            for r in range(N_READS):
                s += gain[i, r] * nu[r]
            x[k, i] += s
        if settled and tick > S.invalid_until and math.isfinite(d2):
            S.stat[k] += B.lam * (pymin(d2, P.fdi.clip_sq) - S.stat[k])
        if S.stat[k] > B.level:
            above |= 1 << k
    S.above = above


@njit
def decide(P, S, tick: int, detected: bool, flat_failed: int, act: int, snapshot,
           cur_held: bool = False) -> int:
    """The episode's decision this tick (the module's doc): ISOLATED_*, NOT_ISOLATED or
    ACTUATOR_* when one is reported now, else NONE. ``flat_failed``: the flatline tests'
    failed channels (bits in BLIND's order); ``act``: the actuator test's failure this tick
    (ACT_STUCK_BIT, ACT_OPEN_BIT); ``snapshot``: the freeze frame a detection now would take
    (kept for the decision's DTC: the state the fault appeared in, not the one it was named
    in); ``cur_held``: the current's reading is held or clipped this tick."""
    B = P.bank
    S.reported = False
    if S.episode < 0:
        if S.decided != NONE:               # a decision stands until detection is quiet
            if detected or flat_failed or act:
                S.quiet_since = -1
            elif S.quiet_since < 0:
                S.quiet_since = tick
            elif tick - S.quiet_since >= P.fdi.settle_ticks:
                S.decided, S.quiet_since = NONE, -1
            return NONE
        if not (detected or flat_failed or act):
            return NONE
        S.episode, S.cleared, S.alone_since, S.act, S.cur_held = tick, 0, -1, 0, False
        S.snapshot[:] = snapshot
        S.quiet_since = -1
    # the evidence ended: no test failing and no filter above its level for settle_ticks
    if detected or flat_failed or act or S.above:
        S.quiet_since = -1
    elif S.quiet_since < 0:
        S.quiet_since = tick
    ended = S.quiet_since >= 0 and tick - S.quiet_since >= P.fdi.settle_ticks
    S.cleared |= S.above
    S.cur_held = S.cur_held or cur_held
    if act and not S.act:
        S.act_since = tick
    S.act |= act
    out = NONE
    left = 0xF & ~S.cleared
    alone = -1                              # the one sensor left, once it stayed so
    if left and left & (left - 1) == 0:
        if S.alone_since < 0:
            S.alone_since = tick
        if tick - S.alone_since >= B.confirm_ticks:
            alone = 0
            while not (left >> alone) & 1:
                alone += 1
    else:
        S.alone_since = -1
    if flat_failed:
        S.decided = BY_TEST                 # (the flatline's own DTC names the channel)
    elif S.act:
        # the actuator test advances the back-EMF with BA - WA: a BA or WA fault the bank
        # names was what it saw. The current left alone (its readers inconsistent, the
        # current-blind filter not) is the current sensor or the actuator: not isolated.
        # The current-blind filter inconsistent too (the corner's force was wrong, which no
        # current sensor fault does): the actuator, once BA and WA are cleared. Else the
        # test's conclusion stands after act_ticks where the bank saw nothing; what only
        # some filters saw is not isolated, and so is anything the test concluded from a
        # current reading held or clipped at its rail (the sensor's own range)
        late = tick - S.act_since >= B.act_ticks or ended
        if alone == ISOLATED_BA or alone == ISOLATED_WA:
            S.decided = out = alone
        elif alone == ISOLATED_CUR:
            S.decided = out = NOT_ISOLATED
        elif not S.cur_held and (
                (not (left & SENSOR_CUR) and not (left & (SENSOR_BA | SENSOR_WA)))
                or (late and (S.cleared == 0 or not (left & SENSOR_CUR)))):
            S.decided = out = ACTUATOR_OPEN if S.act & ACT_OPEN_BIT else ACTUATOR_STUCK
        elif late:
            S.decided = out = NOT_ISOLATED
    elif left == 0:
        S.decided = out = NOT_ISOLATED
    elif alone >= 0:
        S.decided = out = alone
    elif tick - S.episode >= B.decide_ticks or ended:
        S.decided = out = NOT_ISOLATED
    if S.decided != NONE:
        S.candidates = 0xF & ~S.cleared
        S.episode, S.quiet_since = -1, -1
    S.reported = out != NONE
    return out


@njit
def isolate(P, S, tick, ba, wa, defl, i_meas, force_meas, lifted, inputs_ok, failed,
            snapshot) -> None:
    """Stage 2b's isolation (``firmware.ecu``; ``S`` the ECU's state): the filters' tick,
    then the episode's decision, reported as its test's failure in ``S.fdi`` (the DTC that
    names the part, or says none can be named). ``failed``: the tests' failed bits this
    tick; ``snapshot``: the freeze frame a detection now takes."""
    F, B = P.fdi, S.bank
    z = B.z
    z[0], z[1], z[2], z[3] = ba, defl, wa, i_meas
    held = 0
    for bit, c in ((0, adc.BA), (1, adc.DEFL), (2, adc.WA), (3, adc.CUR)):
        if not adc.measured(S.adc, c):
            held |= 1 << bit
    gq = S.grade.gq
    q = P.akf.road_intensity_per_mps * S.adc.value[adc.SPEED] * (
        gq / P.akf_q_gq_nominal if math.isfinite(gq) else 1.0)
    band = abs(force_meas) * F.force_band
    model_ok = (inputs_ok and not lifted and abs(defl) <= F.valid_defl_m
                and abs(i_meas) < P.plant.current_limit - 5.0 * F.cur_sigma_a)
    filters(P, B, tick, z, held, S.fdi.v1, bool(S.fdi.en1), q, band * band / 12.0,
                 model_ok, tick >= F.settle_ticks)
    flat = 0
    for j, t in enumerate(fdi.FLAT_TESTS):
        if (failed >> t) & 1:
            flat |= 1 << j
    act = ((ACT_STUCK_BIT if (failed >> fdi.T_ACT_STUCK) & 1 else 0)
           | (ACT_OPEN_BIT if (failed >> fdi.T_ACT_OPEN) & 1 else 0))
    out = decide(P, B, tick, (failed & fdi.NIS_TESTS) != 0, flat, act, snapshot,
                 (held >> 3) & 1 != 0)
    if out != NONE:
        if out == NOT_ISOLATED:
            t = fdi.T_NOT_ISOLATED
        elif out == ACTUATOR_STUCK:
            t = fdi.T_NAME_ACT_STUCK
        elif out == ACTUATOR_OPEN:
            t = fdi.T_NAME_ACT_OPEN
        else:
            t = fdi.T_ISO_BA + out
        S.fdi.failed |= 1 << t
        S.fdi.completed |= 1 << t
