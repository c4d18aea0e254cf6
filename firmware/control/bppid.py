"""BP-neural-network PID (paper Eq. (27)-(38), errata 13).

A 4-5-3 network with inputs [r, y, e, 1] (normalised), tanh hidden layer and output layer
g(x) = e^x / (e^x + e^-x) = (1 + tanh x) / 2 in (0, 1). The outputs, scaled to the plant's
units, are K_p, K_i, K_d of the incremental PID. Online learning of E = e^2 / 2 by gradient
descent with momentum, sgn(dy/du) for the unknown plant gradient (BA rises with the force:
+1). The derivative of g is g' = 2 g (1 - g); of tanh, 1 - f^2 (errata 13).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware.control import pid
from firmware.jit import njit
from firmware.params import ControlParams

FORCE_REF_N = 100.0   # normalises du/dO in the learning rule


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


def init(p: ControlParams) -> BpPidState:
    return BpPidState(p.bp_w_hidden.copy(), p.bp_b_hidden.copy(), p.bp_w_out.copy(),
                      p.bp_b_out.copy(), np.zeros_like(p.bp_w_hidden), np.zeros_like(p.bp_b_hidden),
                      np.zeros_like(p.bp_w_out), np.zeros_like(p.bp_b_out), pid.PidState(),
                      np.zeros(3), np.zeros(p.bp_w_hidden.shape[1]),
                      np.zeros(p.bp_w_hidden.shape[0]), np.zeros(p.bp_w_out.shape[0]))


def step(p: ControlParams, st: BpPidState, ba: float, dt: float, learn: bool = True) -> float:
    y = ba / p.bp_input_scale
    _forward(st.w_h, st.b_h, st.w_o, st.b_o, y, p.bp_scale, st.x, st.h, st.g, st.gains)
    e_si = -ba
    d_p, d_i, d_d = pid.terms(st.pid, e_si, dt)
    kp, ki, kd = st.gains.tolist()
    u = pid.step(st.pid, e_si, kp, ki, kd, p.pid_leak, dt, p.force_limit)
    if learn:
        _learn(st.w_h, st.b_h, st.w_o, st.b_o, st.dw_h, st.db_h, st.dw_o, st.db_o, st.x, st.h,
               st.g, p.bp_scale, -y, d_p, d_i, d_d, p.bp_alpha, p.bp_eta)
    return u


# -- compiled kernels (firmware.jit); the network's arrays are updated in place -------------
@njit
def _forward(w_h, b_h, w_o, b_o, y, scale, x, h, g, gains):
    """x = [r, y, e, 1] (r = 0, e = -y), h = tanh(W_h x + b_h), g = (1 + tanh(W_o h + b_o)) / 2,
    gains = scale g."""
    x[0], x[1], x[2], x[3] = 0.0, y, -y, 1.0
    for i in range(w_h.shape[0]):
        s = 0.0
        for j in range(w_h.shape[1]):
            s += w_h[i, j] * x[j]
        h[i] = math.tanh(s + b_h[i])
    for k in range(w_o.shape[0]):
        s = 0.0
        for i in range(w_o.shape[1]):
            s += w_o[k, i] * h[i]
        g[k] = 0.5 * (1.0 + math.tanh(s + b_o[k]))
        gains[k] = scale[k] * g[k]


@njit
def _learn(w_h, b_h, w_o, b_o, dw_h, db_h, dw_o, db_o, x, h, g, scale, e, d_p, d_i, d_d,
           alpha, eta):
    """One gradient step with momentum on E = e^2 / 2:
    delta_o = e sgn(dy/du) du/dO g'(net_o) with du/dO = scale du/dK / FORCE_REF_N and
    g' = 2 g (1 - g); delta_h = (1 - h^2) W_o^T delta_o (with W_o before this step);
    dW = alpha dW + eta outer(delta, input); W += dW."""
    no, nh = w_o.shape
    du = (d_p, d_i, d_d)
    delta_o = np.empty(no)
    for k in range(no):
        delta_o[k] = e * (scale[k] * du[k] / FORCE_REF_N) * (2.0 * g[k] * (1.0 - g[k]))
    delta_h = np.empty(nh)
    for i in range(nh):
        s = 0.0
        for k in range(no):
            s += w_o[k, i] * delta_o[k]
        delta_h[i] = (1.0 - h[i] * h[i]) * s
    for k in range(no):
        for i in range(nh):
            dw_o[k, i] = alpha * dw_o[k, i] + eta * (delta_o[k] * h[i])
        db_o[k] = alpha * db_o[k] + eta * delta_o[k]
    for i in range(nh):
        for j in range(w_h.shape[1]):
            dw_h[i, j] = alpha * dw_h[i, j] + eta * (delta_h[i] * x[j])
        db_h[i] = alpha * db_h[i] + eta * delta_h[i]
    for k in range(no):
        for i in range(nh):
            w_o[k, i] += dw_o[k, i]
        b_o[k] += db_o[k]
    for i in range(nh):
        for j in range(w_h.shape[1]):
            w_h[i, j] += dw_h[i, j]
        b_h[i] += db_h[i]
