"""Stages 5-6 in float, compiled: the controller of the active mode with its crossfade
(``firmware.control``), the final gate (``firmware.safety.force_allowed``) and the actuator
stage (``firmware.actuator``: force -> current reference -> H-bridge voltage -> Q15 duty).
The controllers: PID and BP-PID (``firmware.control.pid``, ``bppid``), LQR and GA-LQR
(u = -K x), skyhook, the energy-feedback damping law."""

from __future__ import annotations

import numpy as np

from firmware.actuator import CURRENT_MARGIN, DUTY_MAX_Q15, DUTY_MIN_Q15, Q15_ONE
from firmware.kernels import bppid as bp_kern
from firmware.kernels import njit
from firmware.params import (CTRL_BPPID, CTRL_GALQR, CTRL_LQR, CTRL_NONE, CTRL_PID, CTRL_REGEN,
                             CTRL_SKYHOOK)
from firmware.tick.util import clamp, pymax, pymin, round_half_away

PID = np.dtype([("e1", "f8"), ("e2", "f8"), ("u", "f8")])


def bppid_dtype(n_in: int, n_hidden: int, n_out: int) -> np.dtype:
    return np.dtype([
        ("w_h", "f8", (n_hidden, n_in)), ("b_h", "f8", (n_hidden,)),
        ("w_o", "f8", (n_out, n_hidden)), ("b_o", "f8", (n_out,)),
        ("dw_h", "f8", (n_hidden, n_in)), ("db_h", "f8", (n_hidden,)),
        ("dw_o", "f8", (n_out, n_hidden)), ("db_o", "f8", (n_out,)),
        ("pid", PID), ("gains", "f8", (3,)),
        ("x", "f8", (n_in,)), ("h", "f8", (n_hidden,)), ("g", "f8", (n_out,)),  # learning's
        ("k_pid", "f8", (3,)),       # the gains the PID uses: the network's, low-passed
        ("fresh", "u1"),             # the next step seeds k_pid with the network's gains
        ("delta_o", "f8", (n_out,)), ("delta_h", "f8", (n_hidden,)),   # (learning's deltas)
    ])


ACTUATOR = np.dtype([("integ", "f8"), ("i_ref_prev", "f8"), ("voltage", "f8"),
                     ("i_prev", "f8"), ("observer_valid", "u1"), ("emf", "f8")])


def state_dtype(n_in: int, n_hidden: int, n_out: int) -> np.dtype:
    return np.dtype([
        ("bppid", bppid_dtype(n_in, n_hidden, n_out)), ("pid", PID),
        ("ctrl", "i8"),              # controller now driving
        ("ctrl_from", "i8"),         # controller being faded out
        ("ramp", "i8"),              # ticks into the crossfade
        ("actuator", ACTUATOR),
        ("force_known_prev", "f8"),  # the known force (actuator, bump stops), last tick
    ])


def init(P, S, initial_ctrl: int) -> None:
    b = S.bppid
    b.w_h[:], b.b_h[:], b.w_o[:], b.b_o[:] = P.bp_w_hidden, P.bp_b_hidden, P.bp_w_out, \
        P.bp_b_out
    b.fresh = True
    S.ctrl = initial_ctrl


# ---------------------------------------------------------------- controllers


@njit
def pid_terms(S, e: float, dt: float):
    """The three increments that multiply K_p, K_i, K_d (also du/dK for the BP network)."""
    return e - S.e1, e * dt, (e - 2.0 * S.e1 + S.e2) / dt


@njit
def pid_step(S, e: float, kp: float, ki: float, kd: float, leak: float, dt: float,
             limit: float) -> float:
    tp, ti, td = pid_terms(S, e, dt)
    u = leak * S.u + kp * tp + ki * ti + kd * td
    S.u = clamp(u, -limit, limit)       # anti-windup: the state never exceeds the limit
    S.e2, S.e1 = S.e1, e
    return S.u


@njit
def bppid_step(P, S, ba: float, dt: float) -> float:
    y = ba / P.bp_input_scale
    bp_kern.forward(S.w_h, S.b_h, S.w_o, S.b_o, y, P.bp_scale, S.x, S.h, S.g, S.gains)
    e_si = -ba
    d_p, d_i, d_d = pid_terms(S.pid, e_si, dt)
    if S.fresh:
        S.k_pid[:] = S.gains
        S.fresh = False
    else:
        for k in range(3):
            S.k_pid[k] += P.bp_gain_alpha * (S.gains[k] - S.k_pid[k])
    u = pid_step(S.pid, e_si, S.k_pid[0], S.k_pid[1], S.k_pid[2], P.pid_leak, dt,
                 P.force_limit)
    bp_kern.learn_into(S.w_h, S.b_h, S.w_o, S.b_o, S.dw_h, S.db_h, S.dw_o, S.db_o, S.x, S.h,
                       S.g, P.bp_scale, -y, d_p, d_i, d_d, P.bp_alpha, P.bp_eta, S.delta_o,
                       S.delta_h)
    return u


@njit
def lqr_force(k, x) -> float:
    """u = -K x (the sum in index order: numpy's dot of two 5-vectors gives the same bits)."""
    s = 0.0
    for i in range(5):
        s += k[i] * x[i]
    return -s


@njit
def force_of(P, S, ctrl: int, x, ba: float, dt: float) -> float:
    """The force (N) of controller ``ctrl``."""
    if ctrl == CTRL_PID:
        return pid_step(S.pid, -ba, P.pid_kp, P.pid_ki, P.pid_kd, P.pid_leak, dt,
                        P.force_limit)
    if ctrl == CTRL_BPPID:
        return bppid_step(P, S.bppid, ba, dt) + lqr_force(P.k_comfort, x)
    if ctrl == CTRL_LQR:
        return lqr_force(P.k_safety, x)
    if ctrl == CTRL_GALQR:
        return lqr_force(P.k_comprehensive, x)
    if ctrl == CTRL_SKYHOOK:
        return -P.skyhook_c * x[0] - P.skyhook_passive_c * (x[0] - x[1])
    if ctrl == CTRL_REGEN:
        body_vel, rel_vel = x[0], x[0] - x[1]
        f = -P.regen_c * rel_vel - P.regen_skyhook_c * body_vel
        return 0.0 if f * rel_vel > 0.0 else f
    return 0.0          # CTRL_NONE and anything unknown


@njit
def command(P, S, want: int, ramp_ticks: int, x, ba: float, dt: float) -> float:
    """The force of controller ``want``, crossfaded from the previous controller over
    ``ramp_ticks`` after a change, limited to the force limit."""
    if want != S.ctrl:
        S.ctrl_from, S.ctrl, S.ramp = S.ctrl, want, 0
        if want == CTRL_PID:
            S.pid.u = 0.0
        elif want == CTRL_BPPID:
            S.bppid.pid.u = 0.0
            S.bppid.fresh = True
    force = force_of(P, S, S.ctrl, x, ba, dt)
    if S.ramp < ramp_ticks:
        S.ramp += 1
        beta = S.ramp / ramp_ticks
        force = beta * force + (1.0 - beta) * force_of(P, S, S.ctrl_from, x, ba, dt)
    lim = P.force_limit
    return clamp(force, -lim, lim)


# ---------------------------------------------------------------- actuator


@njit
def current_reference(pl, force: float, rel_vel: float, compensate: bool) -> float:
    demand = force + (pl.friction * rel_vel if compensate else 0.0)
    g = pl.efficiency if demand * rel_vel >= 0.0 else 1.0 / pl.efficiency
    i_ref = demand / (g * pl.force_constant)
    lim = CURRENT_MARGIN * pl.current_limit
    return clamp(i_ref, -lim, lim)


@njit
def duty_to_q15(duty: float) -> int:
    return pymin(DUTY_MAX_Q15, pymax(DUTY_MIN_Q15, round_half_away(duty * Q15_ONE)))


@njit
def actuator_step(A, pl, S, i_ref: float, i_meas: float, rel_vel: float, regen: bool,
                  min_ratio: float, rel_acc: float, dt: float) -> int:
    """Voltage for this tick from the current reference; returns the duty in Q15."""
    if S.observer_valid:
        emf = S.voltage - (i_meas - A.current_a * S.i_prev) / A.current_b
        emf += pl.force_constant * rel_acc * dt
    else:
        emf = pl.force_constant * (rel_vel + 0.5 * dt * rel_acc)
    S.emf = emf
    v_dc = pl.storage_voltage if regen else pl.bus_voltage
    # the integral learns the model error seen on the last tick's reference
    v_ff = emf + (i_ref - A.current_a * i_meas) / A.current_b
    v = v_ff + S.integ
    lo, hi = -v_dc, v_dc
    if regen:
        r = min_ratio * emf
        a, b = (emf, r) if emf < r else (r, emf)     # (sorted((r, emf)))
        lo, hi = pymax(lo, a), pymin(hi, b)
    saturated = v < lo or v > hi
    v = clamp(v, lo, hi)
    if not saturated:
        S.integ += A.ki * (S.i_ref_prev - i_meas)
        S.integ = clamp(S.integ, -A.integ_limit, A.integ_limit)
    S.i_ref_prev = i_ref
    duty = duty_to_q15(v / v_dc)
    S.voltage = duty / Q15_ONE * v_dc      # what the bridge applies (quantised duty)
    S.i_prev = i_meas
    S.observer_valid = True
    return duty


@njit
def actuator_reset(S) -> None:
    S.integ = 0.0
    S.i_ref_prev = 0.0
    S.voltage = 0.0
    S.observer_valid = False
