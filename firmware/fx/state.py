"""The fixed-point path's state (C: ``fx_state_t``, ``fx_init``) and one tick's inputs
(``fx_in_t``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from firmware.fx.tables import FxTables
from firmware.params import CTRL_NONE


@dataclass
class FxPid:
    e1: int = 0
    e2: int = 0
    u: int = 0


@dataclass
class FxState:
    x: list = field(default_factory=lambda: [0] * 5)
    resid: list = field(default_factory=lambda: [0] * 3)
    ba: int = 0
    wa: int = 0
    defl: int = 0
    cur: int = 0
    force_meas: int = 0
    force_known_prev: int = 0     # the known force (actuator, bump stops) of the last tick
    # control
    ctrl: int = CTRL_NONE
    ctrl_from: int = CTRL_NONE
    ramp: int = 0
    pid: FxPid = field(default_factory=FxPid)
    bp_pid: FxPid = field(default_factory=FxPid)
    w_h: list = field(default_factory=list)
    b_h: list = field(default_factory=list)
    w_o: list = field(default_factory=list)
    b_o: list = field(default_factory=list)
    dw_h: list = field(default_factory=lambda: [0] * 20)
    db_h: list = field(default_factory=lambda: [0] * 5)
    dw_o: list = field(default_factory=lambda: [0] * 15)
    db_o: list = field(default_factory=lambda: [0] * 3)
    gains: list = field(default_factory=lambda: [0] * 3)
    k_pid: list = field(default_factory=lambda: [0] * 3)   # the PID's: gains, low-passed
    bp_fresh: bool = True                                  # seed k_pid at the next step
    # actuator
    integ: int = 0
    i_ref_prev: int = 0
    voltage: int = 0
    i_prev: int = 0
    observer_valid: bool = False
    force: int = 0
    duty: int = 0
    gain_saturations: int = 0


def init(T: FxTables, initial_ctrl: int) -> FxState:
    """C: ``fx_init``."""
    s = FxState(ctrl=initial_ctrl)
    s.w_h = [w.m for w in T.bp_w_hidden]
    s.b_h = [w.m for w in T.bp_b_hidden]
    s.w_o = [w.m for w in T.bp_w_out]
    s.b_o = [w.m for w in T.bp_b_out]
    return s


@dataclass(frozen=True)
class TickIn:
    """Everything the fixed-point path takes in one tick (a line of the parity trace; C:
    ``fx_in_t``)."""

    counts: tuple         # 4 x int or None
    k_q: tuple            # 5*m gain mantissas
    r_q: tuple            # m bias mantissas
    want: int
    passive: bool
    fault: bool
    regen: bool
    reset: bool = False   # the float supervisor reset the estimate (non-finite covariance)


def outputs(s: FxState) -> tuple:
    """The integers compared with C on every tick."""
    return (s.duty, s.force, *s.x, *s.resid, s.integ, s.voltage)
