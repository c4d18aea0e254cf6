"""The controllers' fixed-point twins: each file is the integer form of the float controller of
the same name in ``firmware/control/``, function for function the C of ``c/ecu_fx.c``.

Here, as ``firmware.control.command`` is for the float path, the integer control step
(C: ``force_of``, ``fx_control``, ``fx_tick``): the controller of the active mode through a
dispatch table, crossfade, force limit, the final gate (``firmware.safety.force_allowed``) and
the actuator stage; ``tick`` is one whole tick of the fixed-point path (the parity replay)."""

from __future__ import annotations

from firmware import safety
from firmware.control.fx import bppid, lqr, pid, regen, skyhook
from firmware.fixedpoint import add, clamp, div_round, neg, sat32, sub
from firmware.fx import actuator
from firmware.fx.akf import correct, measure, reset_estimate
from firmware.fx.state import FxState, TickIn, outputs
from firmware.fx.tables import F_ACC, F_FORCE, FxTables, cm
from firmware.params import (CTRL_BPPID, CTRL_GALQR, CTRL_LQR, CTRL_NONE, CTRL_PID, CTRL_REGEN,
                             CTRL_SKYHOOK)

# controller -> force (Q(F_FORCE)) from the tables and the state (C: the switch in force_of)
FORCE = {
    CTRL_NONE: lambda T, s: 0,
    CTRL_PID: lambda T, s: pid.pid_step(T, s.pid, neg(s.ba), T.pid_kp.m, T.pid_ki.m,
                                        T.pid_kd.m)[0],
    CTRL_BPPID: lambda T, s: add(bppid.bppid_step(T, s), lqr.force(T.k_comfort, s.x)),
    CTRL_LQR: lambda T, s: lqr.force(T.k_safety, s.x),
    CTRL_GALQR: lambda T, s: lqr.force(T.k_comprehensive, s.x),
    CTRL_SKYHOOK: lambda T, s: skyhook.force(T, s.x),
    CTRL_REGEN: lambda T, s: regen.force(T, s.x),
}


def force_of(T: FxTables, s: FxState, ctrl: int) -> int:
    f = FORCE.get(ctrl)
    return 0 if f is None else f(T, s)


def control(T: FxTables, s: FxState, want: int, passive: bool, fault: bool, regen: bool) -> tuple:
    """Controller ``want`` (of the active mode) with a crossfade from the previous one; the
    actuator stage. Returns (duty_q15, enable, force Q(F_FORCE)). C: ``fx_control``."""
    if want != s.ctrl:
        s.ctrl_from, s.ctrl, s.ramp = s.ctrl, want, 0
        if want == CTRL_PID:
            s.pid.u = 0
        elif want == CTRL_BPPID:
            s.bp_pid.u = 0
            s.bp_fresh = True
    force = force_of(T, s, s.ctrl)
    n = T.ramp_ticks
    if s.ramp < n:
        s.ramp += 1
        f_from = force_of(T, s, s.ctrl_from)
        force = sat32(div_round(s.ramp * force + (n - s.ramp) * f_from, n))
    lim = T.force_limit.m
    force = clamp(force, -lim, lim)
    active = safety.force_allowed(passive, s.ramp < n, fault)
    if active:
        x = s.x
        rel = sub(x[0], x[1])
        i_ref = actuator.current_reference(T, force, rel, not regen)
        rel_acc = add(sub(s.ba, s.wa), cm(T.inv_mass, sub(force, s.force_meas), F_FORCE, F_ACC))
        duty = actuator.step(T, s, i_ref, rel, regen, rel_acc)
    else:
        actuator.reset(s)
        duty, force = 0, 0
    s.force, s.duty = force, duty
    return duty, active, force


def tick(T: FxTables, s: FxState, inp: TickIn) -> tuple:
    """measure, correct and control in one call, with the gain taken from the input
    (C: ``fx_tick``; the parity test's replay)."""
    measure(T, s, inp.counts)
    correct(T, s, list(inp.k_q), list(inp.r_q))
    if inp.reset:
        reset_estimate(s)
    control(T, s, inp.want, inp.passive, inp.fault, inp.regen)
    return outputs(s)
