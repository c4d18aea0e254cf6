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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware.params import (GRADE_UNKNOWN, MODE_COMFORT, MODE_COMPREHENSIVE, MODE_ENERGY,
                             MODE_PASSIVE, MODE_SAFETY, REQ_ACCEPT, REQ_CHOOSE, REQ_REFUSE,
                             ModeParams)

GRADE_TO_MODE = (MODE_ENERGY, MODE_COMFORT, MODE_SAFETY, MODE_COMPREHENSIVE)
N_MODES = 5

REASON_NONE = 0
REASON_ROAD_HOLDING = 1      # safety override: tyre deflection over the limit
REASON_FAULT = 2             # fail-safe: a safety-relevant fault is active

# events of the last step (bit field, reported in the status)
EVT_ACCEPTED = 1
EVT_REFUSED = 2
EVT_CHOSEN = 4
EVT_INVALID_REQUEST = 8
EVT_REQUEST_RATE = 16        # a new request came too soon after the previous one: ignored


@dataclass
class ModeState:
    user_mode: int
    active_mode: int
    recommended: int
    last_counter: int = -1
    override: bool = False
    override_ticks: int = 0
    reason: int = REASON_NONE
    events: int = 0
    refused_mode: int = -1
    ticks: int = 0               # steps taken
    last_request_tick: int = -(1 << 30)   # step of the previous new request
    dtd2_ema: float = 0.0        # tyre-deflection mean square (road-holding check)


def init(params: ModeParams) -> ModeState:
    m = params.initial_mode
    return ModeState(user_mode=m, active_mode=m, recommended=m)


def road_holding_rms(params: ModeParams, st: ModeState, dtd_est: float) -> float:
    """The tyre-deflection RMS of the road-holding check: an exponential mean square over
    ``safety_window_ticks``."""
    alpha = 1.0 / params.safety_window_ticks
    st.dtd2_ema += alpha * (dtd_est * dtd_est - st.dtd2_ema)
    return math.sqrt(st.dtd2_ema)


def step(params: ModeParams, st: ModeState, grade: int, req_kind: int, req_mode: int,
         req_counter: int, dtd_rms: float, fault: bool) -> int:
    st.events = 0
    st.ticks += 1
    if grade != GRADE_UNKNOWN:
        st.recommended = GRADE_TO_MODE[grade]
    if req_counter != st.last_counter:
        st.last_counter = req_counter
        too_soon = (req_kind != 0
                    and st.ticks - st.last_request_tick < params.request_min_ticks)
        if req_kind != 0:
            st.last_request_tick = st.ticks
        if too_soon:
            st.events |= EVT_REQUEST_RATE
        elif req_kind == REQ_ACCEPT:
            if req_mode == st.recommended:
                st.user_mode = st.recommended
                st.events |= EVT_ACCEPTED
            else:
                st.events |= EVT_INVALID_REQUEST   # accepting a stale recommendation
        elif req_kind == REQ_REFUSE:
            st.refused_mode = st.recommended
            st.events |= EVT_REFUSED
        elif req_kind == REQ_CHOOSE:
            if isinstance(req_mode, int) and 0 <= req_mode < N_MODES:
                st.user_mode = req_mode
                st.events |= EVT_CHOSEN
            else:
                st.events |= EVT_INVALID_REQUEST
        elif req_kind != 0:
            st.events |= EVT_INVALID_REQUEST
    # safety first
    if st.override:
        st.override_ticks += 1
        if (dtd_rms < params.safety_dtd_rms_limit * params.safety_exit_ratio
                and st.override_ticks >= params.safety_hold_ticks):
            st.override = False
    elif dtd_rms > params.safety_dtd_rms_limit:
        st.override, st.override_ticks = True, 0
    if fault:
        st.reason = REASON_FAULT
        st.active_mode = MODE_PASSIVE
    elif st.override:
        st.reason = REASON_ROAD_HOLDING
        st.active_mode = MODE_SAFETY
    else:
        st.reason = REASON_NONE
        st.active_mode = st.user_mode
    return st.active_mode
