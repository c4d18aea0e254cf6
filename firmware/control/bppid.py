"""BP-neural-network PID (paper Eq. (27)-(38), errata 13).

A 4-5-3 network with inputs [r, y, e, 1] (normalised), tanh hidden layer and output layer
g(x) = e^x / (e^x + e^-x) = (1 + tanh x) / 2 in (0, 1). The outputs, scaled to the plant's
units, are K_p, K_i, K_d of the incremental PID. Online learning of E = e^2 / 2 by gradient
descent with momentum, sgn(dy/du) for the unknown plant gradient (BA rises with the force:
+1). The derivative of g is g' = 2 g (1 - g); of tanh, 1 - f^2 (errata 13).

The PID takes the network's gains through a first-order low-pass (``bp_gain_alpha`` per tick,
a time constant of seconds; seeded with the network's output when the controller starts):
the network's gains follow BA, and gains that change within a body cycle rectify it. The
integral term K_i(BA) e dt then has a mean, E[K_i(BA) BA] != 0, which the integrator turned
into a static force (about 30 N on the default car: the body 2 mm lower, SWS up to 20 %
above the design). A gain that moves slowly against the signal it multiplies does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware.control import pid
from firmware.kernels import bppid as kern
from firmware.params import ControlParams

FORCE_REF_N = kern.FORCE_REF_N   # normalises du/dO in the learning rule


@dataclass
class BpPidState:
    w_h: np.ndarray
    b_h: np.ndarray
    w_o: np.ndarray
    b_o: np.ndarray
    dw_h: np.ndarray
    db_h: np.ndarray
    dw_o: np.ndarray
    db_o: np.ndarray
    pid: pid.PidState
    gains: np.ndarray
    x: np.ndarray         # the last input, hidden and output activations (the learning's)
    h: np.ndarray
    g: np.ndarray
    k_pid: np.ndarray     # the gains the PID uses: the network's, low-passed
    fresh: bool = True    # the next step seeds k_pid with the network's gains


def init(p: ControlParams) -> BpPidState:
    return BpPidState(p.bp_w_hidden.copy(), p.bp_b_hidden.copy(), p.bp_w_out.copy(),
                      p.bp_b_out.copy(), np.zeros_like(p.bp_w_hidden), np.zeros_like(p.bp_b_hidden),
                      np.zeros_like(p.bp_w_out), np.zeros_like(p.bp_b_out), pid.PidState(),
                      np.zeros(3), np.zeros(p.bp_w_hidden.shape[1]),
                      np.zeros(p.bp_w_hidden.shape[0]), np.zeros(p.bp_w_out.shape[0]),
                      np.zeros(3))


def step(p: ControlParams, st: BpPidState, ba: float, dt: float, learn: bool = True) -> float:
    y = ba / p.bp_input_scale
    kern.forward(st.w_h, st.b_h, st.w_o, st.b_o, y, p.bp_scale, st.x, st.h, st.g, st.gains)
    e_si = -ba
    d_p, d_i, d_d = pid.terms(st.pid, e_si, dt)
    if st.fresh:
        st.k_pid[:] = st.gains
        st.fresh = False
    else:
        st.k_pid += p.bp_gain_alpha * (st.gains - st.k_pid)
    kp, ki, kd = st.k_pid.tolist()
    u = pid.step(st.pid, e_si, kp, ki, kd, p.pid_leak, dt, p.force_limit)
    if learn:
        kern.learn(st.w_h, st.b_h, st.w_o, st.b_o, st.dw_h, st.db_h, st.dw_o, st.db_o, st.x, st.h,
               st.g, p.bp_scale, -y, d_p, d_i, d_d, p.bp_alpha, p.bp_eta)
    return u
