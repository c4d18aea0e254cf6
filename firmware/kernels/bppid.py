"""The BP-PID network's compiled kernels (``firmware.control`` is the controller): the
forward pass and one learning step, the network's arrays updated in place."""

from __future__ import annotations

import math


from firmware.kernels import njit

FORCE_REF_N = 100.0   # normalises du/dO in the learning rule


@njit
def forward(w_h, b_h, w_o, b_o, y, scale, x, h, g, gains):
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
def learn_into(w_h, b_h, w_o, b_o, dw_h, db_h, dw_o, db_o, x, h, g, scale, e, d_p, d_i, d_d,
               alpha, eta, delta_o, delta_h):
    """One gradient step with momentum on E = e^2 / 2:
    delta_o = e sgn(dy/du) du/dO g'(net_o) with du/dO = scale du/dK / FORCE_REF_N and
    g' = 2 g (1 - g); delta_h = (1 - h^2) W_o^T delta_o (with W_o before this step);
    dW = alpha dW + eta outer(delta, input); W += dW. ``delta_o``, ``delta_h``: the deltas'
    storage (the compiled tick's, allocated nowhere)."""
    no, nh = w_o.shape
    du = (d_p, d_i, d_d)
    for k in range(no):
        delta_o[k] = e * (scale[k] * du[k] / FORCE_REF_N) * (2.0 * g[k] * (1.0 - g[k]))
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
