"""Road-grade estimation.

Default classifier (errata 12): it looks only at the AKF's estimate of the *road*, in which the
control force is a known input, so it reads the same whichever controller runs. The road
velocity is formed from the well-observed states, wheel velocity minus the rate of the tyre
deflection (the absolute road height itself is only weakly observable, errata 9, and its
estimate jitters along the unobservable common mode); it is band-passed; its variance per block, divided by the variance a unit-G_q road gives
at the current speed (a table computed offline from the road model), estimates G_q. The grade
is log4(G_q / G_q,A) rounded, with hysteresis and a minimum dwell. The window is a fixed number
of blocks, so a grade change is fully seen after one window.

Paper's classifier (Table 2, Eq. (24)-(26)): windowed RMS of the estimated tyre deflection and
of the measured body acceleration against the passive thresholds.

Compiled (numba) over the state record's ``grade`` fields: the window's blocks are a ring
(``blocks_*``, oldest at ``head``), summed oldest first.
"""

from __future__ import annotations

import math

import numpy as np

from firmware.kernels import njit
from firmware.kernels.grade import interp
from firmware.params import GRADE_UNKNOWN

CLASSIFIER_ROAD = 0
CLASSIFIER_PAPER = 1


def state_dtype(n_blocks: int) -> np.dtype:
    return np.dtype([
        ("prev_road", "f8"),           # last tyre-deflection estimate
        ("prev_vel", "f8"), ("hp", "f8"), ("lp", "f8"), ("started", "u1"),
        ("tick_in_block", "i8"),
        ("acc_gq", "f8"),              # sum over the block of band power / variance per G_q
        ("acc_dtd2", "f8"), ("acc_ba2", "f8"),
        ("blocks_gq", "f8", (n_blocks,)), ("blocks_dtd2", "f8", (n_blocks,)),
        ("blocks_ba2", "f8", (n_blocks,)),
        ("filled", "i8"), ("head", "i8"),   # blocks in the window; the oldest's index
        ("grade", "i8"), ("candidate", "i8"), ("candidate_blocks", "i8"),
        ("log_gq", "f8"),              # latest estimate, in grade units (A = 0 ... D = 3)
        ("gq", "f8"), ("dtd_rms", "f8"), ("ba_rms", "f8"),
    ])


def init(S) -> None:
    S.grade = S.candidate = GRADE_UNKNOWN
    S.log_gq = S.gq = math.nan


@njit
def paper_rule(P, dtd_rms: float, ba_rms: float) -> int:
    """Table 2: DTD first (safety), then BA."""
    if dtd_rms < P.dtd1:
        return 0 if ba_rms < P.ba1 else 1
    return 2 if ba_rms <= P.ba2 else 3


@njit
def _window_sum(blocks, head: int, n: int) -> float:
    s = 0.0
    for k in range(n):
        s += blocks[(head + k) % n]
    return s


@njit
def step(P, S, wheel_vel: float, dtd_est: float, ba: float, speed: float, dt: float) -> int:
    """Feed one tick. Returns the current grade (0..3) or GRADE_UNKNOWN."""
    if speed < P.min_speed:
        S.started = False   # standing still: no information; restart the filters on moving off
        return S.grade
    if not S.started:
        S.prev_road, S.prev_vel, S.hp, S.lp, S.started = dtd_est, 0.0, 0.0, 0.0, True
        return S.grade
    vel = wheel_vel - (dtd_est - S.prev_road) / dt   # road velocity estimate
    S.prev_road = dtd_est
    S.hp = P.hp_a * (S.hp + vel - S.prev_vel)
    S.prev_vel = vel
    S.lp += P.lp_a * (S.hp - S.lp)
    S.acc_gq += S.lp * S.lp / interp(speed, P.speed_grid, P.var_per_gq)
    S.acc_dtd2 += dtd_est * dtd_est
    S.acc_ba2 += ba * ba
    S.tick_in_block += 1
    n = P.block_ticks
    if S.tick_in_block < n:
        return S.grade
    # close the block: into the ring (the oldest out once it is full)
    nb = P.n_blocks
    if S.filled < nb:
        at = (S.head + S.filled) % nb
        S.filled += 1
    else:
        at = S.head
        S.head = (S.head + 1) % nb
    S.blocks_gq[at] = S.acc_gq / n
    S.blocks_dtd2[at] = S.acc_dtd2 / n
    S.blocks_ba2[at] = S.acc_ba2 / n
    S.tick_in_block = 0
    S.acc_gq = S.acc_dtd2 = S.acc_ba2 = 0.0
    if S.filled < nb:
        return S.grade
    S.gq = _window_sum(S.blocks_gq, S.head, nb) / nb
    gq = 1e-30 if 1e-30 > S.gq else S.gq          # (Python's max(gq, 1e-30): NaN stays)
    S.log_gq = math.log(gq / P.gq_centres[0]) / math.log(4.0)
    S.dtd_rms = math.sqrt(_window_sum(S.blocks_dtd2, S.head, nb) / nb)
    S.ba_rms = math.sqrt(_window_sum(S.blocks_ba2, S.head, nb) / nb)
    g = float(paper_rule(P, S.dtd_rms, S.ba_rms)) if P.classifier == CLASSIFIER_PAPER \
        else S.log_gq
    nearest = min(3, max(0, int(math.floor(g + 0.5))))
    if S.grade == GRADE_UNKNOWN:
        S.grade = nearest
        return S.grade
    cur = S.grade
    beyond = (g > cur + 0.5 + P.hysteresis) or (g < cur - 0.5 - P.hysteresis)
    if P.classifier == CLASSIFIER_PAPER:
        beyond = nearest != cur
    if beyond and nearest != cur:
        if nearest == S.candidate:
            S.candidate_blocks += 1
        else:
            S.candidate, S.candidate_blocks = nearest, 1
        if S.candidate_blocks * n >= P.dwell_ticks:
            S.grade = nearest
            S.candidate, S.candidate_blocks = GRADE_UNKNOWN, 0
    else:
        S.candidate, S.candidate_blocks = GRADE_UNKNOWN, 0
    return S.grade
