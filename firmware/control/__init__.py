"""Controllers of the working modes, each mapping the ECU's signals to a force command (N):
``pid``, ``bppid`` (comfort), ``lqr`` (safety LQR and comprehensive GA-LQR), ``skyhook``,
``regen`` (energy feedback); their fixed-point twins in ``control.fx``.

``command`` runs the controller of the active mode through the dispatch table ``FORCE``, with a
crossfade over ``ModeParams.ramp_ticks`` when the controller changes (bumpless transfer), and
limits the force."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware.control import bppid, lqr, pid, regen, skyhook
from firmware.params import (CTRL_BPPID, CTRL_GALQR, CTRL_LQR, CTRL_NONE, CTRL_PID, CTRL_REGEN,
                             CTRL_SKYHOOK, ControlParams)


@dataclass
class ControlState:
    bppid: bppid.BpPidState
    pid: pid.PidState
    ctrl: int = CTRL_NONE            # controller now driving
    ctrl_from: int = CTRL_NONE       # controller being faded out
    ramp: int = 0                    # ticks into the crossfade


def init(p: ControlParams, initial_ctrl: int) -> ControlState:
    return ControlState(bppid=bppid.init(p), pid=pid.PidState(), ctrl=initial_ctrl)


# controller -> force (N) from (calibration, state, estimate x, body acceleration, tick)
FORCE = {
    CTRL_NONE: lambda p, cs, x, ba, dt: 0.0,
    CTRL_PID: lambda p, cs, x, ba, dt: pid.step(cs.pid, -ba, p.pid_kp, p.pid_ki, p.pid_kd,
                                                p.pid_leak, dt, p.force_limit),
    CTRL_BPPID: lambda p, cs, x, ba, dt: (bppid.step(p, cs.bppid, ba, dt)
                                          + lqr.force(p.k_comfort, x)),
    CTRL_LQR: lambda p, cs, x, ba, dt: lqr.force(p.k_safety, x),
    CTRL_GALQR: lambda p, cs, x, ba, dt: lqr.force(p.k_comprehensive, x),
    CTRL_SKYHOOK: lambda p, cs, x, ba, dt: skyhook.force(p, x),
    CTRL_REGEN: lambda p, cs, x, ba, dt: regen.force(p, x[0], x[0] - x[1]),
}


def force_of(p: ControlParams, cs: ControlState, ctrl: int, x: np.ndarray, ba: float,
             dt: float) -> float:
    f = FORCE.get(ctrl)
    return 0.0 if f is None else f(p, cs, x, ba, dt)


def command(p: ControlParams, cs: ControlState, want: int, ramp_ticks: int, x: np.ndarray,
            ba: float, dt: float) -> float:
    """The force of controller ``want``, crossfaded from the previous controller over
    ``ramp_ticks`` after a change, limited to the force limit."""
    if want != cs.ctrl:
        cs.ctrl_from, cs.ctrl, cs.ramp = cs.ctrl, want, 0
        if want in (CTRL_PID, CTRL_BPPID):
            pid.reset_to(cs.pid if want == CTRL_PID else cs.bppid.pid, 0.0)
        if want == CTRL_BPPID:
            cs.bppid.fresh = True
    force = force_of(p, cs, cs.ctrl, x, ba, dt)
    if cs.ramp < ramp_ticks:
        cs.ramp += 1
        beta = cs.ramp / ramp_ticks
        force = beta * force + (1.0 - beta) * force_of(p, cs, cs.ctrl_from, x, ba, dt)
    lim = p.force_limit
    return min(lim, max(-lim, force))
