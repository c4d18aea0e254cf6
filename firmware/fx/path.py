"""The fixed-point path's stages 2 and 5-6, compiled: the integer half of the Kalman filter
(ADC counts to Q signals, the prediction, the residual, the correction with the gain the
float half hands over), the controllers and the actuator, function for function the C of
``c/ecu_fx.c`` (``firmware/fx/__init__.py`` has the table). The tables record ``T`` is
``calib.fx_tables.build_tables``'s ``FxTables`` laid out by ``firmware.layout``: a constant is
``T.name.m``/``T.name.frac``, a table of them ``T.name.m[i]``/``.frac[i]``."""

from __future__ import annotations

import math

import numpy as np

from firmware.fx.tables import (ADC_FRAC, F_ACC, F_CUR, F_FORCE, F_JERK, F_NN, F_POS, F_TANH,
                                F_VEL, F_VOLT, F_W, MEAS_FRAC, ONE_NN, STATE_FRAC, TANH_N,
                                TANH_STEP_BITS)
from firmware.kernels import njit
from firmware.params import (CTRL_BPPID, CTRL_GALQR, CTRL_LQR, CTRL_PID, CTRL_REGEN,
                             CTRL_SKYHOOK)
from firmware.fixedpoint import (INT32_MAX, INT32_MIN, add, clamp, cm, cmi, div_round, mul, neg,
                                 rshift_round, same_sign_or_zero, sat16, sat32, sub, to_fixed)

PID = np.dtype([("e1", "i8"), ("e2", "i8"), ("u", "i8")])


def state_dtype(m: int) -> np.dtype:
    """C: ``fx_state_t`` (and what the float half hands over, ``fx_in_t``'s k and r)."""
    return np.dtype([
        ("x", "i8", (5,)), ("resid", "i8", (m,)),
        ("ba", "i8"), ("wa", "i8"), ("defl", "i8"), ("cur", "i8"),
        ("force_meas", "i8"), ("force_known_prev", "i8"),
        ("ctrl", "i8"), ("ctrl_from", "i8"), ("ramp", "i8"), ("pid", PID), ("bp_pid", PID),
        ("w_h", "i8", (20,)), ("b_h", "i8", (5,)), ("w_o", "i8", (15,)), ("b_o", "i8", (3,)),
        ("dw_h", "i8", (20,)), ("db_h", "i8", (5,)), ("dw_o", "i8", (15,)), ("db_o", "i8", (3,)),
        ("gains", "i8", (3,)), ("k_pid", "i8", (3,)), ("bp_fresh", "u1"),
        ("integ", "i8"), ("i_ref_prev", "i8"), ("voltage", "i8"), ("i_prev", "i8"),
        ("observer_valid", "u1"), ("force", "i8"), ("duty", "i8"),
        ("gain_saturations", "i8"),
        # this tick's hand-over from the float half (the parity trace's k, r, reset)
        ("counts", "i8", (4,)), ("k_q", "i8", (5 * m,)), ("r_q", "i8", (m,)), ("reset", "u1"),
        # (what the float half took in and gave: the C estimator's replay, c/akf_cov.c)
        ("q_road", "f8"), ("cov_flags", "i8"), ("k_f", "f8", (5 * m,)),
        ("want", "i8"), ("passive", "u1"), ("fault", "u1"), ("regen", "u1"),
        # (scratch: the network's input, hidden and output activations, deltas)
        ("xin", "i8", (4,)), ("h", "i8", (5,)), ("g", "i8", (3,)), ("d_o", "i8", (3,)),
        ("d_h", "i8", (5,)), ("xp", "i8", (5,)), ("eps", "i8", (m,)),
    ])


def init(T, S, initial_ctrl: int) -> None:
    """C: ``fx_init``."""
    S.ctrl = initial_ctrl
    S.w_h[:], S.b_h[:] = T.bp_w_hidden.m, T.bp_b_hidden.m
    S.w_o[:], S.b_o[:] = T.bp_w_out.m, T.bp_b_out.m
    S.bp_fresh = True


# ---------------------------------------------------------------- the filter's integer half


@njit
def adc_signal(T, k: int, counts: int) -> int:
    """C: ``adc_signal`` (counts -1: no good sample yet)."""
    if counts < 0:
        return 0
    return add(T.adc_off.m[k], cmi(T.adc_lsb, k, counts, 0, ADC_FRAC[k]))


@njit
def bump_force(T, defl: int) -> int:
    """C: ``bump_force``."""
    if T.bump_k.m == 0:
        return 0
    if defl > T.bump_clear.m:
        return neg(cm(T.bump_k, sub(defl, T.bump_clear.m), F_POS, F_FORCE))
    if defl < -T.bump_clear.m:
        return neg(cm(T.bump_k, add(defl, T.bump_clear.m), F_POS, F_FORCE))
    return 0


@njit
def measure(T, S, counts) -> None:
    """C: ``fx_measure``: counts -> signals; the prediction with the force that acted over the
    last tick; the residual z - H x_pred - D u."""
    S.ba, S.wa = adc_signal(T, 0, counts[0]), adc_signal(T, 1, counts[1])
    S.defl, S.cur = adc_signal(T, 2, counts[2]), adc_signal(T, 3, counts[3])
    x = S.x
    rel_prev = sub(x[0], x[1])
    if same_sign_or_zero(S.cur, rel_prev):
        S.force_meas = cm(T.kf_eta, S.cur, F_CUR, F_FORCE)
    else:
        S.force_meas = cm(T.kf_over_eta, S.cur, F_CUR, F_FORCE)
    known = add(S.force_meas, bump_force(T, S.defl))      # the actuator's and the bump stops'
    u = sat32(rshift_round(S.force_known_prev + known, 1))
    S.force_known_prev = known
    xp = S.xp
    for i in range(5):
        acc = cmi(T.gamma, i, u, F_FORCE, STATE_FRAC[i])
        for j in range(5):
            acc += cmi(T.phi, 5 * i + j, x[j], STATE_FRAC[j], STATE_FRAC[i])
        xp[i] = sat32(acc)
    x[:] = xp
    for i in range(T.n_meas):
        z = S.ba if i == 0 else S.defl if i == 1 else S.wa
        acc = z - cmi(T.d, i, known, F_FORCE, MEAS_FRAC[i])
        for j in range(5):
            acc -= cmi(T.h, 5 * i + j, xp[j], STATE_FRAC[j], MEAS_FRAC[i])
        S.resid[i] = sat32(acc)


@njit
def quantize_gain(T, S, K) -> None:
    """The float gain K (5 x m) as Q numbers in the table's formats into ``S.k_q`` (a
    non-finite gain hands over 0: the ECU flags the non-finite covariance in the same tick
    and resets the filter); saturations counted."""
    m = T.n_meas
    for idx in range(5 * m):
        v = K[idx // m, idx % m]
        S.k_f[idx] = v
        q = to_fixed(v, T.k_frac[idx]) if math.isfinite(v) else 0
        if q == INT32_MAX or q == INT32_MIN:
            S.gain_saturations += 1
        S.k_q[idx] = q


@njit
def correct(T, S) -> None:
    """C: ``fx_correct``: x += K (residual - r)."""
    m = T.n_meas
    eps = S.eps
    for j in range(m):
        eps[j] = sub(S.resid[j], S.r_q[j]) if T.bias_adaptive else S.resid[j]
    x = S.x
    for i in range(5):
        acc = x[i]
        for j in range(m):
            acc += mul(S.k_q[m * i + j], eps[j],
                       T.k_frac[m * i + j] + MEAS_FRAC[j] - STATE_FRAC[i])
        x[i] = sat32(acc)


# ---------------------------------------------------------------- the controllers


@njit
def tanh_q(T, v: int) -> int:
    """C: ``tanh_q``: LUT over [0, 8] in steps of 2^-7, linear interpolation, odd symmetry."""
    a = -v if v < 0 else v
    sh = F_NN - TANH_STEP_BITS
    idx = a >> sh
    lut = T.tanh_lut
    if idx >= TANH_N:
        t = lut[TANH_N]
    else:
        t = lut[idx] + rshift_round((lut[idx + 1] - lut[idx]) * (a & ((1 << sh) - 1)), sh)
    t = rshift_round(t, F_TANH - F_NN)
    return -t if v < 0 else t


@njit
def pid_step(T, S, e: int, kp: int, ki: int, kd: int):
    """C: ``pid_step``: returns (u, tp, ti, td)."""
    tp = sub(e, S.e1)
    ti = cm(T.dt, e, F_ACC, F_VEL)
    td = cm(T.inv_dt, sat32(e - 2 * S.e1 + S.e2), F_ACC, F_JERK)
    u = (cm(T.pid_leak, S.u, F_FORCE, F_FORCE) + mul(kp, tp, T.f_kp + F_ACC - F_FORCE)
         + mul(ki, ti, T.f_ki + F_VEL - F_FORCE) + mul(kd, td, T.f_kd + F_JERK - F_FORCE))
    lim = T.force_limit.m
    S.u = clamp(sat32(u), -lim, lim)
    S.e2, S.e1 = S.e1, e
    return S.u, tp, ti, td


@njit
def learn_layer(T, w, dw, b, db, deltas, n_out: int, inputs, n_in: int) -> None:
    """C: ``learn_layer``: gradient step with momentum of one layer."""
    for r in range(n_out):
        ed = cm(T.bp_eta, deltas[r], F_W, F_W)
        for j in range(n_in):
            n = n_in * r + j
            dw[n] = add(cm(T.bp_alpha, dw[n], F_W, F_W), mul(ed, inputs[j], F_NN))
            w[n] = add(w[n], dw[n])
        db[r] = add(cm(T.bp_alpha, db[r], F_W, F_W), ed)
        b[r] = add(b[r], db[r])


@njit
def gain_format(T, k: int) -> int:
    return T.f_kp if k == 0 else T.f_ki if k == 1 else T.f_kd


@njit
def bppid_step(T, S) -> int:
    """C: ``bppid_step``."""
    y = cm(T.bp_inv_input_scale, S.ba, F_ACC, F_NN)
    e = neg(y)
    xin, h, g = S.xin, S.h, S.g
    xin[0], xin[1], xin[2], xin[3] = 0, y, e, ONE_NN
    for i in range(5):
        acc = rshift_round(S.b_h[i], F_W - F_NN)
        for j in range(4):
            acc += mul(S.w_h[4 * i + j], xin[j], F_W)
        h[i] = tanh_q(T, sat32(acc))
    for k in range(3):
        acc = rshift_round(S.b_o[k], F_W - F_NN)
        for i in range(5):
            acc += mul(S.w_o[5 * k + i], h[i], F_W)
        g[k] = sat32(rshift_round(ONE_NN + tanh_q(T, sat32(acc)), 1))
    for k in range(3):
        S.gains[k] = cmi(T.bp_scale, k, g[k], F_NN, gain_format(T, k))
    if S.bp_fresh:                    # the PID's gains: the network's, low-passed
        S.k_pid[:] = S.gains
        S.bp_fresh = False
    else:
        for k in range(3):
            gf = gain_format(T, k)
            S.k_pid[k] = add(S.k_pid[k], cm(T.bp_gain_alpha, sub(S.gains[k], S.k_pid[k]), gf,
                                            gf))
    u, tp, ti, td = pid_step(T, S.bp_pid, neg(S.ba), S.k_pid[0], S.k_pid[1], S.k_pid[2])
    # learning (firmware.control's BP-PID): deltas and weight steps in Q(F_W)
    for k in range(3):
        du, du_f = (tp, F_ACC) if k == 0 else (ti, F_VEL) if k == 1 else (td, F_JERK)
        a_k = cmi(T.bp_du_scale, k, du, du_f, F_NN)
        gp = mul(g[k], ONE_NN - g[k], F_NN - 1)               # g' = 2 g (1 - g)
        S.d_o[k] = mul(mul(e, a_k, F_NN), gp, 2 * F_NN - F_W)
    for i in range(5):
        back = 0
        for k in range(3):
            back += mul(S.w_o[5 * k + i], S.d_o[k], F_W)
        one_m_h2 = ONE_NN - mul(h[i], h[i], F_NN)
        S.d_h[i] = mul(one_m_h2, sat32(back), F_NN)
    learn_layer(T, S.w_o, S.dw_o, S.b_o, S.db_o, S.d_o, 3, h, 5)
    learn_layer(T, S.w_h, S.dw_h, S.b_h, S.db_h, S.d_h, 5, xin, 4)
    return u


@njit
def lqr_force(ks, x) -> int:
    """C: ``lqr_force``: -K x, each product from the state's format to the force's."""
    acc = 0
    for j in range(5):
        acc += cmi(ks, j, x[j], STATE_FRAC[j], F_FORCE)
    return neg(sat32(acc))


@njit
def force_of(T, S, ctrl: int) -> int:
    """C: the switch in ``force_of``."""
    x = S.x
    if ctrl == CTRL_PID:
        return pid_step(T, S.pid, neg(S.ba), T.pid_kp.m, T.pid_ki.m, T.pid_kd.m)[0]
    if ctrl == CTRL_BPPID:
        return add(bppid_step(T, S), lqr_force(T.k_comfort, x))
    if ctrl == CTRL_LQR:
        return lqr_force(T.k_safety, x)
    if ctrl == CTRL_GALQR:
        return lqr_force(T.k_comprehensive, x)
    if ctrl == CTRL_SKYHOOK:
        return neg(sat32(cm(T.skyhook_c, x[0], F_VEL, F_FORCE)
                         + cm(T.skyhook_passive_c, sub(x[0], x[1]), F_VEL, F_FORCE)))
    if ctrl == CTRL_REGEN:
        rel = sub(x[0], x[1])
        f = neg(sat32(cm(T.regen_c, rel, F_VEL, F_FORCE)
                      + cm(T.regen_skyhook_c, x[0], F_VEL, F_FORCE)))
        return 0 if (f > 0 and rel > 0) or (f < 0 and rel < 0) else f
    return 0


@njit
def current_reference(T, force: int, rel: int, compensate: bool) -> int:
    """C: ``current_reference``."""
    demand = add(force, cm(T.friction, rel, F_VEL, F_FORCE)) if compensate else force
    if same_sign_or_zero(demand, rel):
        i_ref = cm(T.inv_eta_kf, demand, F_FORCE, F_CUR)
    else:
        i_ref = cm(T.eta_over_kf, demand, F_FORCE, F_CUR)
    lim = T.current_limit.m
    return clamp(i_ref, -lim, lim)


@njit
def actuator_step(T, S, i_ref: int, rel: int, regen: bool, rel_acc: int) -> int:
    """C: ``actuator_step``."""
    i_meas = S.cur
    if S.observer_valid:
        emf = sub(S.voltage, cm(T.inv_cur_b, sub(i_meas, cm(T.cur_a, S.i_prev, F_CUR, F_CUR)),
                                F_CUR, F_VOLT))
        emf = add(emf, cm(T.kf_dt, rel_acc, F_ACC, F_VOLT))
    else:
        emf = cm(T.kf, add(rel, cm(T.half_dt, rel_acc, F_ACC, F_VEL)), F_VEL, F_VOLT)
    if regen:
        v_dc, per_m, per_frac = T.v_storage.m, T.duty_per_v_storage.m, T.duty_per_v_storage.frac
    else:
        v_dc, per_m, per_frac = T.v_bus.m, T.duty_per_v_bus.m, T.duty_per_v_bus.frac
    v_ff = add(emf, cm(T.inv_cur_b, sub(i_ref, cm(T.cur_a, i_meas, F_CUR, F_CUR)), F_CUR,
                       F_VOLT))
    v = add(v_ff, S.integ)
    lo, hi = -v_dc, v_dc
    if regen:
        r = cm(T.regen_min_ratio, emf, F_VOLT, F_VOLT)
        a, b = (r, emf) if r <= emf else (emf, r)
        lo, hi = max(lo, a), min(hi, b)
    saturated = v < lo or v > hi
    v = min(hi, max(lo, v))
    if not saturated:
        il = T.integ_limit.m
        S.integ = clamp(add(S.integ, cm(T.cur_ki, sub(S.i_ref_prev, i_meas), F_CUR, F_VOLT)),
                        -il, il)
    S.i_ref_prev = i_ref
    duty = sat16(rshift_round(v * per_m, per_frac + F_VOLT))
    S.voltage = sat32(rshift_round(duty * v_dc, 15))
    S.i_prev = i_meas
    S.observer_valid = True
    return duty


@njit
def actuator_reset(S) -> None:
    """C: ``actuator_reset``."""
    S.integ = 0
    S.i_ref_prev = 0
    S.voltage = 0
    S.observer_valid = False


@njit
def control(T, S, want: int, passive: bool, fault: bool, regen: bool):
    """C: ``fx_control``: controller ``want`` with a crossfade from the previous one, the
    force limit, the gate, the actuator. Returns (duty_q15, enable, force Q(F_FORCE))."""
    if want != S.ctrl:
        S.ctrl_from, S.ctrl, S.ramp = S.ctrl, want, 0
        if want == CTRL_PID:
            S.pid.u = 0
        elif want == CTRL_BPPID:
            S.bp_pid.u = 0
            S.bp_fresh = True
    force = force_of(T, S, S.ctrl)
    n = T.ramp_ticks
    if S.ramp < n:
        S.ramp += 1
        f_from = force_of(T, S, S.ctrl_from)
        force = sat32(div_round(S.ramp * force + (n - S.ramp) * f_from, n))
    lim = T.force_limit.m
    force = clamp(force, -lim, lim)
    active = (not passive or S.ramp < n) and not fault      # the final gate (firmware.ecu._control)
    if active:
        x = S.x
        rel = sub(x[0], x[1])
        i_ref = current_reference(T, force, rel, not regen)
        rel_acc = add(sub(S.ba, S.wa), cm(T.inv_mass, sub(force, S.force_meas), F_FORCE,
                                          F_ACC))
        duty = actuator_step(T, S, i_ref, rel, regen, rel_acc)
    else:
        actuator_reset(S)
        duty, force = 0, 0
    S.force, S.duty = force, duty
    return duty, active, force
