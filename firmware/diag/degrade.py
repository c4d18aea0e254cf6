"""Degraded operation: with one sensor isolated faulty the ECU drives on the others
(docs/degraded.md).

* **Entry**: the isolation names a sensor (the bank's decision, ``firmware.diag.bank``, or
  one flatline test): ``sensor`` is set and the ECU reconfigures.
* **The reduced filter**: before stage 1 the named channel's counts are replaced by a
  virtual sensor, the filter's one-step prediction of that channel (x' = Phi x + Gamma u, the
  model's output H x' + D u, u the known force of the last tick) quantised as its ADC would;
  the filter does not correct with it (its noise is ``akf.SKIP_SCALE`` times R-hat's; R-hat
  adapts on the others), so the estimate is the Kalman filter of the measurements left. It
  restarts from its power-up state at the entry: during the episode the faulty sensor moved
  the estimate, and an offset it left in the road or position states (a bias, a drift) is
  one no sensor left corrects: kept, it held a static force of 130-520 N in comfort.
  Everything downstream (the controllers' BA, the actuator's BA - WA, the grade's BA RMS,
  the tests) reads the virtual value, in both arithmetic paths; the C parity trace carries
  its counts. Without the motor current no mode is kept (its loop and the filter's force
  need it): the bridge opens at once (the plausibility bit is held), the virtual current is
  the open bridge's zero.
* **The tests restart** on the reduced filter: the innovation, actuator and bank statistics
  start again and hold ``FdiParams.hold_ticks``; the named channel's own tests (innovation,
  flatline; the actuator test without BA or WA, which it advances the back-EMF with) no
  longer report.
* **Modes**: ``DegradeParams.modes[sensor]`` are the modes kept (measured without that
  sensor: ``python -m tools.degraded``); the others fall back to passive
  (``firmware.modes.REASON_DEGRADED``).
* **Readmission and latching**: the sensor out is still watched: its reading against the
  virtual one, normalised by their variance (the filter's H P H' of that channel, the
  sensor's noise, the force band), through the innovation tests' EWMA. Below their level for
  ``readmit_ticks`` (the fault went away), it is used again (the tests restart), once per
  operation cycle; named a second time in a cycle it stays out to the cycle's end
  (``latched``). A fault that persists keeps it out. A clear of every DTC (the workshop's)
  starts the count of namings afresh (``firmware.diag.view.DiagView.clear``).
* **A second fault** (any detection test failing after the restart, with a sensor out): the
  fail-safe latches to the end of the operation cycle.
* **Healing**: an ECU reset (a new cycle) starts normal, every sensor used and tested again
  (a fault still there is isolated again). The DTCs stay stored over cycles and age as ISO
  14229 says (``firmware.diag.dtc``: 40 cycles without a failure).

Compiled (numba) over the state record's ``degrade`` fields.
"""

from __future__ import annotations

import math

import numpy as np

from firmware import adc, akf
from firmware.akf import MEASURED
from firmware.diag import bank, fdi
from firmware.kernels import njit
from firmware.params import MODE_NAMES
from firmware.util import pymin
from firmware.util import round_half_away as rha

NONE = -1
# the named sensor (bank order: BA, WA, SWS, current) -> the ADC channel it is
CHANNEL = (adc.BA, adc.WA, adc.DEFL, adc.CUR)
SENSOR_NAMES = ("body_accel", "wheel_accel", "susp_defl", "motor_current")
CURRENT = 3
# each sensor's own tests (no verdict of theirs counts once it is out)
OWN_TESTS = ((1 << fdi.T_NIS_BA) | (1 << fdi.T_FLAT_BA),
             (1 << fdi.T_NIS_WA) | (1 << fdi.T_FLAT_WA),
             (1 << fdi.T_NIS_SWS) | (1 << fdi.T_FLAT_SWS),
             (1 << fdi.T_FLAT_CUR))
# a second fault: a detection test failing (the bank's decisions follow detections)
DETECTIONS = (fdi.NIS_TESTS | fdi.ACT_TESTS | (1 << fdi.T_FLAT_BA) | (1 << fdi.T_FLAT_WA)
              | (1 << fdi.T_FLAT_SWS) | (1 << fdi.T_FLAT_CUR))
# the state on the bus (ECU_STATUS.DEGRADED) and in DID 0x0107
STATE_NORMAL, STATE_DEGRADED, STATE_FAIL_SAFE, STATE_LATCHED = 0, 1, 2, 3
STATE_NAMES = ("normal", "sensor_out", "fail_safe_latched", "sensor_out_latched")  # (the DBC's)
Z_INDEX = tuple(MEASURED.index(c) if c in MEASURED else -1 for c in CHANNEL)   # its z row
ALL_MODES = (1 << len(MODE_NAMES)) - 1   # bit m: mode m (firmware.params.MODE_*)

STATE = np.dtype([
    ("sensor", "i8"),                    # the sensor out (NONE: all in use)
    ("pending", "i8"),                   # left out by hand, taken out next tick (NONE: none)
    ("latched", "u1"),                   # ... to the end of the cycle (named twice in it)
    ("failsafe", "u1"),                  # latched fail-safe (a second fault)
    ("since", "i8"),                     # tick it went out (-1: none)
    ("restart", "i8"),                   # the restarted tests report from this tick
    ("second", "i8"),                    # tick of the second fault (-1: none) ...
    ("second_tests", "i8"),              # ... and the tests that failed then (fdi bits)
    ("named", "i8", (4,)),               # times each sensor was named this cycle
    ("reading", "f8"), ("twin", "f8"),  # its reading this tick (NaN: none), the twin's
    ("stat", "f8"),                      # the sensor out against the filter (EWMA) ...
    ("ok_since", "i8"),                  # ... below the level since this tick (-1: not)
    ("u_prev", "f8"),                    # the known force of the last tick (N) ...
    ("du", "f8"),                        # ... and its change over that tick
    ("xp", "f8", (5,)),                  # (scratch: the one-step prediction ...
    ("counts", "i8", (adc.N,)),          #  ... and the counts the ADC stage takes)
])


def init(S) -> None:
    S.sensor = S.pending = NONE
    S.since = S.restart = S.second = S.ok_since = -1


@njit
def state_code(S) -> int:
    """ECU_STATUS.DEGRADED of the state record ``S`` (``code``)."""
    return code(S.failsafe, S.sensor, S.latched)


@njit
def code(failsafe: bool, sensor: int, latched: bool) -> int:
    """ECU_STATUS.DEGRADED (and DID 0x0107's state): normal, a sensor out, the fail-safe
    latched, a sensor out to the cycle's end (``STATE_NAMES``)."""
    if failsafe:
        return STATE_FAIL_SAFE
    if sensor == NONE:
        return STATE_NORMAL
    return STATE_LATCHED if latched else STATE_DEGRADED


@njit
def substitute(P, S, received):
    """Before stage 1: the counts the ADC stage takes, the received ones with the sensor
    out's channel the virtual sensor's (where a sample arrived: no sample stays the frame's
    fault); the sensor out watched for its readmission. ``S``: the ECU's state."""
    D = S.degrade
    counts = D.counts
    counts[:] = received
    j = D.sensor if D.pending == NONE else D.pending
    if j == NONE:
        return counts
    c = CHANNEL[j]
    if counts[c] == adc.NO_SAMPLE:
        return counts
    if j == CURRENT:                     # (never driving: the bridge is open, no current)
        value = 0.0
    else:
        x, A, xp = S.akf.x, P.akf, D.xp
        for i in range(5):
            s = A.gamma[i] * D.u_prev
            for k in range(5):
                s += A.phi[i, k] * x[k]
            xp[i] = s
        value = P.degrade.D[j] * D.u_prev
        for k in range(5):
            value += P.degrade.H[j, k] * xp[k]
    a = P.adc
    n = min(max(rha((value - a.range_min[c]) / a.lsb[c]), 1), a.full_scale[c] - 1)
    real = counts[c]                     # (a rail would be the ADC's fault: not at one)
    D.reading = a.range_min[c] + real * a.lsb[c] if 0 < real < a.full_scale[c] else math.nan
    D.twin = a.range_min[c] + n * a.lsb[c]
    counts[c] = n
    return counts


@njit
def known_force(D, u: float) -> None:
    """After stage 2: the tick's known force (the next tick's virtual sensor takes it)."""
    D.du, D.u_prev = u - D.u_prev, u


@njit
def watch(P, S, force_meas: float, rho: float) -> None:
    """Stage 2b: the sensor out against the filter that does not use it, as the innovation
    test would take it (its innovation, H P H' rho + R0 + D^2 var_F); below the test's
    level for ``readmit_ticks`` it is used again from the next tick. The motor current: its
    reading against the open bridge's zero. Not where the filter lacks the channel (WA in a
    two-measurement filter), nor latched."""
    D, F = S.degrade, P.fdi
    j = D.sensor
    if j == NONE or D.latched or not math.isfinite(D.reading):
        return
    if j == CURRENT:
        resid, var = D.reading, F.cur_sigma_a * F.cur_sigma_a
    else:
        z = Z_INDEX[j]
        if z >= S.akf.R.shape[0]:
            return
        band = abs(force_meas) * F.force_band
        d = P.akf.D[z]
        resid = S.akf.innovation[z] + D.reading - D.twin
        var = (S.akf.hph[z] * rho + P.akf.r0[z, z]
               + d * d * (band * band / 12.0 + 0.25 * D.du * D.du))
    D.stat += F.nis_lambda * (pymin(resid * resid / var, F.clip_sq) - D.stat)
    if not D.stat <= F.nis_threshold:
        D.ok_since = -1
        return
    if D.ok_since < 0:
        D.ok_since = S.tick
    if S.tick - D.ok_since < P.degrade.readmit_ticks:
        return
    D.sensor, D.since, D.ok_since = NONE, -1, -1
    _restart_tests(P, S, S.tick)
    B = S.bank
    B.episode, B.decided, B.quiet_since, B.alone_since = -1, bank.NONE, -1, -1


@njit
def enter(P, S, j: int, tick: int) -> None:
    """Reconfigure for sensor ``j`` out: the filter restarts from its power-up state on the
    sensors left (the faulty sensor moved its estimate during the episode, and an offset it
    left in the road or position states is one no sensor left corrects), the tests restart
    on the reduced filter."""
    akf.init(P.akf, S.akf)
    S.fx.x[:] = 0                        # (the fixed-point path's: the parity trace's reset)
    S.fx.reset = True
    S.fx.cov_flags |= akf.COV_RESTART    # (and the C estimator's replay: its restart)
    D = S.degrade
    D.sensor, D.since, D.ok_since = j, tick, -1
    D.named[j] += 1
    D.latched = D.named[j] > P.degrade.readmissions
    D.stat = P.fdi.clip_sq               # (it must come down: a window of agreement)
    _restart_tests(P, S, tick)


@njit
def _restart_tests(P, S, tick: int) -> None:
    """The innovation, actuator and bank statistics start again and hold ``hold_ticks``."""
    D, F, B = S.degrade, S.fdi, S.bank
    D.restart = tick + P.fdi.hold_ticks
    F.nis[:] = 1.0
    F.nis_failed = 0
    F.invalid_until = max(F.invalid_until, tick + P.fdi.hold_ticks)
    F.flat_run[:] = 0
    F.act, F.act_onset, F.act_latched, F.act_until = 1.0, -1, 0, -1
    F.emf_known = False                  # (learnt again from the current's response)
    B.stat[:] = 1.0
    B.invalid_until = max(B.invalid_until, tick + P.fdi.hold_ticks)


@njit
def bridge_blocked(S) -> bool:
    """No active force at all: the motor current out, or the fail-safe latched (the
    plausibility bit is held)."""
    return S.degrade.failsafe or S.degrade.sensor == CURRENT


@njit
def named(S, failed: int) -> int:
    """The sensor the isolation named this tick (bank order), NONE if none."""
    B = S.bank
    if B.reported and bank.ISOLATED_BA <= B.decided <= bank.ISOLATED_CUR:
        return B.decided
    flat = NONE
    for j in range(4):
        if (failed >> fdi.FLAT_TESTS[j]) & 1:
            if flat != NONE:
                return NONE              # (two at once: no single sensor)
            flat = j
    return flat


@njit
def silence(S, failed: int) -> int:
    """The sensor out's own tests report nothing this tick (``S.fdi``); returns ``failed``
    without them."""
    own = 0 if S.degrade.sensor == NONE else OWN_TESTS[S.degrade.sensor]
    S.fdi.failed &= ~own
    S.fdi.completed &= ~own
    return failed & ~own


def leave_out(Sa, sensor: str) -> None:
    """The sensor by name (SENSOR_NAMES) out to the end of the cycle (``latched``: what
    the ECU does without it), from the next tick on: its channel is the virtual sensor's from
    that tick's stage 1, and ``enter`` acts in its stage 2b, where a naming by the isolation
    bank does (``take_out``). Between ticks it would restart the filter unseen by the
    fixed-point path's record (the next tick's hand-over starts clean): the C estimator's
    replay would not restart, and C would part from Python."""
    if sensor not in SENSOR_NAMES:
        raise ValueError(f"unknown sensor {sensor!r} (one of {', '.join(SENSOR_NAMES)})")
    Sa[0]["degrade"]["pending"] = SENSOR_NAMES.index(sensor)


@njit
def take_out(P, S, tick: int) -> None:
    """Stage 2b, first: a sensor left out by hand (``leave_out``) goes out, latched."""
    j = S.degrade.pending
    if j == NONE:
        return
    S.degrade.pending = NONE
    enter(P, S, j, tick)
    S.degrade.latched = True


@njit
def step(P, S, tick: int) -> None:
    """After stage 2b's tests and isolation (``S.fdi.failed``, the sensor out's own tests
    silenced; ``S.bank``): enter the degraded state on an isolation, latch the fail-safe on
    a second fault."""
    D = S.degrade
    failed = S.fdi.failed
    if D.sensor == NONE:
        if not D.failsafe:
            j = named(S, failed)
            if j != NONE:
                enter(P, S, j, tick)
    elif tick >= D.restart and failed & DETECTIONS and not D.failsafe:
        D.failsafe, D.second, D.second_tests = True, tick, failed & DETECTIONS


@njit
def kept_modes(P, S) -> int:
    """The modes the state allows (bits of firmware.params.MODE_*; passive always)."""
    D = S.degrade
    if D.failsafe:
        return 1
    if D.sensor == NONE:
        return ALL_MODES
    return P.degrade.modes[D.sensor] | 1
