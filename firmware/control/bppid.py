"""BP-neural-network PID (paper Eq. (27)-(38), errata 13).

A 4-5-3 network with inputs [r, y, e, 1] (normalised), tanh hidden layer and output layer
g(x) = e^x / (e^x + e^-x) = (1 + tanh x) / 2 in (0, 1). The outputs, scaled to the plant's
units, are K_p, K_i, K_d of the incremental PID. Online learning of E = e^2 / 2 by gradient
descent with momentum, sgn(dy/du) for the unknown plant gradient (BA rises with the force:
+1). The derivative of g is g' = 2 g (1 - g); of tanh, 1 - f^2 (errata 13).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware.control import pid
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


def init(p: ControlParams) -> BpPidState:
    return BpPidState(p.bp_w_hidden.copy(), p.bp_b_hidden.copy(), p.bp_w_out.copy(),
                      p.bp_b_out.copy(), np.zeros_like(p.bp_w_hidden), np.zeros_like(p.bp_b_hidden),
                      np.zeros_like(p.bp_w_out), np.zeros_like(p.bp_b_out), pid.PidState(),
                      np.zeros(3))


def step(p: ControlParams, st: BpPidState, ba: float, dt: float, learn: bool = True) -> float:
    y = ba / p.bp_input_scale
    e = -y
    x = np.array([0.0, y, e, 1.0])
    h = np.tanh(st.w_h @ x + st.b_h)
    net_o = st.w_o @ h + st.b_o
    g = 0.5 * (1.0 + np.tanh(net_o))
    st.gains = p.bp_scale * g
    e_si = -ba
    du_dk = np.array(pid.terms(st.pid, e_si, dt))
    u = pid.step(st.pid, e_si, st.gains[0], st.gains[1], st.gains[2], p.pid_leak, dt,
                 p.force_limit)
    if learn:
        # delta_l = e * sgn(dy/du) * du/dO_l * g'(net_l), du/dO_l = scale_l * du/dK_l
        delta_o = e * (p.bp_scale * du_dk / FORCE_REF_N) * (2.0 * g * (1.0 - g))
        delta_h = (1.0 - h * h) * (st.w_o.T @ delta_o)
        st.dw_o = p.bp_alpha * st.dw_o + p.bp_eta * np.outer(delta_o, h)
        st.db_o = p.bp_alpha * st.db_o + p.bp_eta * delta_o
        st.dw_h = p.bp_alpha * st.dw_h + p.bp_eta * np.outer(delta_h, x)
        st.db_h = p.bp_alpha * st.db_h + p.bp_eta * delta_h
        st.w_o += st.dw_o
        st.b_o += st.db_o
        st.w_h += st.dw_h
        st.b_h += st.db_h
    return u
