"""Stage 5, the controllers of the working modes, each mapping the ECU's signals to a force
command (N), and ``command``: the active mode's controller with a crossfade over
``ModeParams.ramp_ticks`` when the controller changes (bumpless transfer), the force limited.
Compiled (numba) over the state record's ``ctl`` fields.

* **PID** on the body acceleration, incremental (errata 13):

      du = K_p (e_k - e_{k-1}) + K_i e_k dt + K_d (e_k - 2 e_{k-1} + e_{k-2}) / dt
      u_k = leak * u_{k-1} + du

  with e = r - y = -BA (reference: no body acceleration). The integral of -BA is minus the
  body velocity, so K_i acts as skyhook damping; the leak (a time constant of seconds, far
  below the body mode) keeps an accelerometer offset from winding the output up.
* **BP-neural-network PID** (comfort; paper Eq. (27)-(38), errata 13): a 4-5-3 network with
  inputs [r, y, e, 1] (normalised), tanh hidden layer and output layer
  g(x) = e^x / (e^x + e^-x) = (1 + tanh x) / 2 in (0, 1). The outputs, scaled to the plant's
  units, are K_p, K_i, K_d of the incremental PID. Online learning of E = e^2 / 2 by gradient
  descent with momentum, sgn(dy/du) for the unknown plant gradient (BA rises with the force:
  +1). The derivative of g is g' = 2 g (1 - g); of tanh, 1 - f^2 (errata 13); the arithmetic
  is ``firmware.kernels.bppid``'s. The PID takes the network's gains through a first-order
  low-pass (``bp_gain_alpha`` per tick, a time constant of seconds; seeded with the network's
  output when the controller starts): the network's gains follow BA, and gains that change
  within a body cycle rectify it. The integral term K_i(BA) e dt then has a mean,
  E[K_i(BA) BA] != 0, which the integrator turned into a static force (about 30 N on the
  default car: the body 2 mm lower, SWS up to 20 % above the design). A gain that moves
  slowly against the signal it multiplies does not. Comfort adds the LQR term of ``k_comfort``.
* **LQR** state feedback u = -K x on the AKF's estimate: safety mode's gain (designed by
  ``calib.design``, LQR with BA and SWS bounded by the passive car's) and comprehensive mode's
  GA-LQR gain (tuned by ``calib.galqr``, Eq. (43)/(44)). The firmware only applies the gain.
* **Skyhook** damping: a force against the body velocity, plus optional added damping on the
  relative velocity (x = [zs', zt', zs, zt, zf]).
* **Energy feedback** (the motor as a generator): a damping law (harvesting damping on the
  relative velocity plus a skyhook part on the body velocity). Only dissipative forces can be
  harvested, so a force that would have to push (F * v_rel > 0) is dropped to zero: a
  semi-active law. The actuator stage (``firmware.actuator``) then keeps the terminal voltage
  where power flows into the storage element.
"""

from __future__ import annotations

import numpy as np

from firmware.actuator import ACTUATOR
from firmware.kernels import bppid as bp_kern
from firmware.kernels import njit
from firmware.params import (CTRL_BPPID, CTRL_GALQR, CTRL_LQR, CTRL_NONE, CTRL_PID, CTRL_REGEN,
                             CTRL_SKYHOOK)
from firmware.util import clamp

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
