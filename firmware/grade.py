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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


from firmware.kernels.grade import interp
from firmware.params import GRADE_UNKNOWN, GradeParams

CLASSIFIER_ROAD = 0
CLASSIFIER_PAPER = 1


@dataclass
class GradeState:
    prev_road: float = 0.0      # last tyre-deflection estimate
    prev_vel: float = 0.0
    hp: float = 0.0
    lp: float = 0.0
    started: bool = False
    tick_in_block: int = 0
    acc_gq: float = 0.0          # sum over the block of band power / (variance per unit G_q)
    acc_dtd2: float = 0.0
    acc_ba2: float = 0.0
    blocks_gq: list = field(default_factory=list)
    blocks_dtd2: list = field(default_factory=list)
    blocks_ba2: list = field(default_factory=list)
    grade: int = GRADE_UNKNOWN
    candidate: int = GRADE_UNKNOWN
    candidate_blocks: int = 0
    log_gq: float = float("nan")  # latest estimate, in grade units (A = 0 ... D = 3)
    gq: float = float("nan")
    dtd_rms: float = 0.0
    ba_rms: float = 0.0


def var_per_gq(params: GradeParams, speed: float) -> float:
    return interp(float(speed), params.speed_grid, params.var_per_gq)


def paper_rule(dtd_rms: float, ba_rms: float, params: GradeParams) -> int:
    """Table 2: DTD first (safety), then BA."""
    if dtd_rms < params.dtd1:
        return 0 if ba_rms < params.ba1 else 1
    return 2 if ba_rms <= params.ba2 else 3


def _continuous_grade(params: GradeParams, st: GradeState) -> float:
    if params.classifier == CLASSIFIER_PAPER:
        return float(paper_rule(st.dtd_rms, st.ba_rms, params))
    return st.log_gq


def step(params: GradeParams, st: GradeState, wheel_vel: float, dtd_est: float, ba: float,
         speed: float, dt: float) -> int:
    """Feed one tick. Returns the current grade (0..3) or GRADE_UNKNOWN."""
    if speed < params.min_speed:
        st.started = False   # standing still: no information; restart the filters on moving off
        return st.grade
    if not st.started:
        st.prev_road, st.prev_vel, st.hp, st.lp, st.started = dtd_est, 0.0, 0.0, 0.0, True
        return st.grade
    vel = wheel_vel - (dtd_est - st.prev_road) / dt   # road velocity estimate
    st.prev_road = dtd_est
    st.hp = params.hp_a * (st.hp + vel - st.prev_vel)
    st.prev_vel = vel
    st.lp += params.lp_a * (st.hp - st.lp)
    st.acc_gq += st.lp * st.lp / var_per_gq(params, speed)
    st.acc_dtd2 += dtd_est * dtd_est
    st.acc_ba2 += ba * ba
    st.tick_in_block += 1
    if st.tick_in_block < params.block_ticks:
        return st.grade
    # close the block
    n = params.block_ticks
    for blocks, value in ((st.blocks_gq, st.acc_gq / n), (st.blocks_dtd2, st.acc_dtd2 / n),
                          (st.blocks_ba2, st.acc_ba2 / n)):
        blocks.append(value)
        if len(blocks) > params.n_blocks:
            blocks.pop(0)
    st.tick_in_block = 0
    st.acc_gq = st.acc_dtd2 = st.acc_ba2 = 0.0
    if len(st.blocks_gq) < params.n_blocks:
        return st.grade
    st.gq = sum(st.blocks_gq) / params.n_blocks
    st.log_gq = (math.log(max(st.gq, 1e-30) / params.gq_centres[0]) / math.log(4.0))
    st.dtd_rms = math.sqrt(sum(st.blocks_dtd2) / params.n_blocks)
    st.ba_rms = math.sqrt(sum(st.blocks_ba2) / params.n_blocks)
    g = _continuous_grade(params, st)
    nearest = min(3, max(0, int(math.floor(g + 0.5))))
    if st.grade == GRADE_UNKNOWN:
        st.grade = nearest
        return st.grade
    cur = st.grade
    beyond = (g > cur + 0.5 + params.hysteresis) or (g < cur - 0.5 - params.hysteresis)
    if params.classifier == CLASSIFIER_PAPER:
        beyond = nearest != cur
    if beyond and nearest != cur:
        if nearest == st.candidate:
            st.candidate_blocks += 1
        else:
            st.candidate, st.candidate_blocks = nearest, 1
        if st.candidate_blocks * n >= params.dwell_ticks:
            st.grade = nearest
            st.candidate, st.candidate_blocks = GRADE_UNKNOWN, 0
    else:
        st.candidate, st.candidate_blocks = GRADE_UNKNOWN, 0
    return st.grade
