"""Working-mode state machine: recommend, let the driver decide, safety first.

* The ECU recommends the mode of the estimated grade: A -> energy feedback, B -> comfort,
  C -> safety, D -> comprehensive.
* It changes the active mode only on a driver request: ACCEPT (of the mode recommended now),
  or CHOOSE (any valid mode). REFUSE leaves the mode as it is. A request is acted on once, when
  its counter changes. A new request less than ``request_min_ticks`` after the previous new
  one (spam: a stuck button, a babbling app) is ignored and reported (EVT_REQUEST_RATE).
* Safety first: when the tyre-deflection RMS exceeds the road-holding limit, the ECU enters
  safety mode whatever was chosen and reports the reason; it returns to the driver's mode when
  the RMS has fallen below limit * exit ratio and the minimum hold has passed.
* Faults (from the safety code) force the fail-safe state: no active force (the bridge is
  opened, passive damping remains).
* With a sensor out (``firmware.diag.degrade``) only the modes it keeps drive; the others
  (the driver's, or the override's safety mode) fall back to passive (REASON_DEGRADED).

Compiled (numba) over the state record's ``modes`` fields.
"""

from __future__ import annotations

import math

import numpy as np

from firmware.kernels import njit
from firmware.params import (GRADE_UNKNOWN, MODE_COMFORT, MODE_COMPREHENSIVE, MODE_ENERGY,
                             MODE_PASSIVE, MODE_SAFETY, REQ_ACCEPT, REQ_CHOOSE, REQ_REFUSE)

GRADE_TO_MODE = (MODE_ENERGY, MODE_COMFORT, MODE_SAFETY, MODE_COMPREHENSIVE)
N_MODES = 5

REASON_NONE = 0
REASON_ROAD_HOLDING = 1      # safety override: tyre deflection over the limit
REASON_FAULT = 2             # fail-safe: a safety-relevant fault is active
REASON_DEGRADED = 3          # the mode is not kept with a sensor out (firmware.diag.degrade)

# events of the last step (bit field, reported in the status)
EVT_ACCEPTED = 1
EVT_REFUSED = 2
EVT_CHOSEN = 4
EVT_INVALID_REQUEST = 8
EVT_REQUEST_RATE = 16        # a new request came too soon after the previous one: ignored
# an ACCEPT of a valid mode the ECU no longer recommends: the recommendation changed while the
# request was on its way (a race of the protocol, not invalid data): ignored, no fault; the
# driver sees the new recommendation and answers it
EVT_STALE_ACCEPT = 32

STATE = np.dtype([
    ("user_mode", "i8"), ("active_mode", "i8"), ("recommended", "i8"),
    ("last_counter", "i8"), ("override", "u1"), ("override_ticks", "i8"), ("reason", "i8"),
    ("events", "i8"), ("refused_mode", "i8"),
    ("ticks", "i8"),                 # steps taken
    ("last_request_tick", "i8"),     # step of the previous new request
    ("dtd2_ema", "f8"),              # tyre-deflection mean square (road-holding check)
])


def init(P, S) -> None:
    m = P.initial_mode
    S.user_mode = S.active_mode = S.recommended = m
    S.last_counter = S.refused_mode = -1
    S.last_request_tick = -(1 << 30)


@njit
def grade_to_mode(grade: int) -> int:
    return (MODE_ENERGY, MODE_COMFORT, MODE_SAFETY, MODE_COMPREHENSIVE)[grade]


@njit
def road_holding_rms(P, S, dtd_est: float) -> float:
    """The tyre-deflection RMS of the road-holding check: an exponential mean square over
    ``safety_window_ticks``."""
    alpha = 1.0 / P.safety_window_ticks
    S.dtd2_ema += alpha * (dtd_est * dtd_est - S.dtd2_ema)
    return math.sqrt(S.dtd2_ema)


@njit
def step(P, S, grade: int, req_kind: int, req_mode: int, req_counter: int, dtd_rms: float,
         fault: bool, kept: int) -> int:
    """One step; ``kept``: the modes the sensors in use support (bits of MODE_*: a mode not
    kept falls back to passive, REASON_DEGRADED)."""
    S.events = 0
    S.ticks += 1
    if grade != GRADE_UNKNOWN:
        S.recommended = grade_to_mode(grade)
    if req_counter != S.last_counter:
        S.last_counter = req_counter
        too_soon = req_kind != 0 and S.ticks - S.last_request_tick < P.request_min_ticks
        if req_kind != 0:
            S.last_request_tick = S.ticks
        if too_soon:
            S.events |= EVT_REQUEST_RATE
        elif req_kind == REQ_ACCEPT:
            if req_mode == S.recommended:
                S.user_mode = S.recommended
                S.events |= EVT_ACCEPTED
            elif 0 <= req_mode < N_MODES:
                S.events |= EVT_STALE_ACCEPT
            else:
                S.events |= EVT_INVALID_REQUEST
        elif req_kind == REQ_REFUSE:
            S.refused_mode = S.recommended
            S.events |= EVT_REFUSED
        elif req_kind == REQ_CHOOSE:
            if 0 <= req_mode < N_MODES:
                S.user_mode = req_mode
                S.events |= EVT_CHOSEN
            else:
                S.events |= EVT_INVALID_REQUEST
        elif req_kind != 0:
            S.events |= EVT_INVALID_REQUEST
    # safety first
    if S.override:
        S.override_ticks += 1
        if (dtd_rms < P.safety_dtd_rms_limit * P.safety_exit_ratio
                and S.override_ticks >= P.safety_hold_ticks):
            S.override = False
    elif dtd_rms > P.safety_dtd_rms_limit:
        S.override = True
        S.override_ticks = 0
    if fault:
        S.reason = REASON_FAULT
        S.active_mode = MODE_PASSIVE
    elif S.override:
        S.reason = REASON_ROAD_HOLDING
        S.active_mode = MODE_SAFETY
    else:
        S.reason = REASON_NONE
        S.active_mode = S.user_mode
    if not (kept >> S.active_mode) & 1:
        S.reason = REASON_DEGRADED
        S.active_mode = MODE_PASSIVE
    return S.active_mode
