"""The BP-PID network in fixed point (C: ``tanh_q``, ``learn_layer``, ``bppid_step``): the
forward pass through the tanh table, the PID with the network's gains (low-passed,
``firmware.control.bppid``), and the learning step in Q(F_W)."""

from __future__ import annotations

from firmware.control.fx.pid import pid_step
from firmware.fixedpoint import add, mul, neg, rshift_round, sat32, sub
from firmware.fx.state import FxState
from firmware.fx.tables import (F_ACC, F_JERK, F_NN, F_TANH, F_VEL, F_W, ONE_NN, TANH_N,
                                TANH_STEP_BITS, FxTables, cm)


def tanh_q(T: FxTables, v: int) -> int:
    """tanh of a Q(F_NN) number, Q(F_NN): LUT over [0, 8] in steps of 2^-7, linear
    interpolation, odd symmetry, saturated beyond 8."""
    a = -v if v < 0 else v
    sh = F_NN - TANH_STEP_BITS
    idx = a >> sh
    if idx >= TANH_N:
        t = T.tanh_lut[TANH_N]
    else:
        lut = T.tanh_lut
        t = lut[idx] + rshift_round((lut[idx + 1] - lut[idx]) * (a & ((1 << sh) - 1)), sh)
    t = rshift_round(t, F_TANH - F_NN)
    return -t if v < 0 else t


def bppid_step(T: FxTables, s: FxState) -> int:
    y = cm(T.bp_inv_input_scale, s.ba, F_ACC, F_NN)
    e = neg(y)
    xin = (0, y, e, ONE_NN)
    h = []
    for i in range(5):
        acc = rshift_round(s.b_h[i], F_W - F_NN)
        for j in range(4):
            acc += mul(s.w_h[4 * i + j], xin[j], F_W)
        h.append(tanh_q(T, sat32(acc)))
    g = []
    for k in range(3):
        acc = rshift_round(s.b_o[k], F_W - F_NN)
        for i in range(5):
            acc += mul(s.w_o[5 * k + i], h[i], F_W)
        g.append(sat32(rshift_round(ONE_NN + tanh_q(T, sat32(acc)), 1)))
    gf = (T.f_kp, T.f_ki, T.f_kd)
    s.gains = [cm(T.bp_scale[k], g[k], F_NN, gf[k]) for k in range(3)]
    if s.bp_fresh:                    # the PID's gains: the network's, low-passed
        s.k_pid = list(s.gains)
        s.bp_fresh = False
    else:
        s.k_pid = [add(s.k_pid[k], cm(T.bp_gain_alpha, sub(s.gains[k], s.k_pid[k]), gf[k],
                                      gf[k])) for k in range(3)]
    u, tp, ti, td = pid_step(T, s.bp_pid, neg(s.ba), *s.k_pid)
    # learning (firmware.control.bppid): deltas and weight steps in Q(F_W)
    du = (tp, ti, td)
    du_f = (F_ACC, F_VEL, F_JERK)
    d_o = []
    for k in range(3):
        a_k = cm(T.bp_du_scale[k], du[k], du_f[k], F_NN)
        gp = mul(g[k], ONE_NN - g[k], F_NN - 1)               # g' = 2 g (1 - g)
        d_o.append(mul(mul(e, a_k, F_NN), gp, 2 * F_NN - F_W))
    d_h = []
    for i in range(5):
        back = sat32(sum(mul(s.w_o[5 * k + i], d_o[k], F_W) for k in range(3)))
        one_m_h2 = ONE_NN - mul(h[i], h[i], F_NN)
        d_h.append(mul(one_m_h2, back, F_NN))
    learn_layer(T, s.w_o, s.dw_o, s.b_o, s.db_o, d_o, h)
    learn_layer(T, s.w_h, s.dw_h, s.b_h, s.db_h, d_h, xin)
    return u


def learn_layer(T: FxTables, w: list, dw: list, b: list, db: list, deltas: list,
                 inputs: tuple | list) -> None:
    """Gradient step with momentum of one layer (row-major weights, one row per delta):
    dw = alpha dw + eta delta input, db = alpha db + eta delta; w += dw, b += db."""
    n_in = len(inputs)
    for r, delta in enumerate(deltas):
        ed = cm(T.bp_eta, delta, F_W, F_W)
        for j in range(n_in):
            n = n_in * r + j
            dw[n] = add(cm(T.bp_alpha, dw[n], F_W, F_W), mul(ed, inputs[j], F_NN))
            w[n] = add(w[n], dw[n])
        db[r] = add(cm(T.bp_alpha, db[r], F_W, F_W), ed)
        b[r] = add(b[r], db[r])
