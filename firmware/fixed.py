"""The fixed-point control path: ADC counts -> scaled signals -> state estimate -> controller
-> PWM duty counts, in integer arithmetic only (``firmware.fixedpoint``). ``c/ecu_fx.c`` is the
same code in C99, using only the generated tables (``make tables``); a test feeds both a
recorded trace and requires identical integers on every tick.

Split of one ECU tick (``firmware.ecu.step`` with ``init(params, fixed=True)``):

  1. ``measure``   counts -> Q signals; measured force; x_pred = Phi x + Gamma u;
                   residual z - H x_pred - D u                                  (integer)
  2. the adaptive part of the Kalman filter in float: from the residual it adapts R-hat,
     computes P and the gain K (``firmware.akf.gain``), handed over as Q numbers
     (``quantize_gain``), as a background task hands its result to the control interrupt
  3. ``correct``   x += K (residual - r)                                        (integer)
  4. road grade, road-holding check and mode logic in float, from x             (supervisor)
  5. ``control``   controller of the selected mode, crossfade, force limit, force -> current
                   -> voltage -> duty, regen bounds                             (integer)

Formats (fractional bits of the int32 signals, the ``F_*`` constants): accelerations Q11.20,
velocities Q7.24, displacements Q3.28, forces Q19.12, currents and voltages Q11.20, jerk Q19.12,
network activations Q7.24, network weights and deltas Q3.28; the duty is Q15 (int16).
A constant is a mantissa with its own fractional bits (``Fx``), chosen offline for the most
precision that fits; a product c*x in format f_x to format f_y shifts by f_c + f_x - f_y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from firmware.fixedpoint import (INT32_MAX, INT32_MIN, add, best_frac, clamp, div_round, mul, neg, rshift_round, sat16,
                                 sat32, sub, to_fixed)
from firmware.params import (CTRL_BPPID, CTRL_GALQR, CTRL_LQR, CTRL_NONE, CTRL_PID, CTRL_REGEN,
                             CTRL_SKYHOOK, EcuParams)

F_ACC = 20
F_VEL = 24
F_POS = 28
F_FORCE = 12
F_CUR = 20
F_VOLT = 20
F_JERK = 12
F_NN = 24
F_W = 28
F_TANH = 30
TANH_STEP_BITS = 7          # LUT step 2^-7 over [0, 8]
TANH_N = 8 << TANH_STEP_BITS
STATE_FRAC = (F_VEL, F_VEL, F_POS, F_POS, F_POS)
MEAS_FRAC = (F_ACC, F_POS, F_ACC)          # z = [BA, SWS, WA][:m]
ADC_FRAC = (F_ACC, F_ACC, F_POS, F_CUR)    # body accel, wheel accel, deflection, current
GAIN_HEADROOM_BITS = 8
FORCE_REF_N = 100.0                        # firmware.control.bppid.FORCE_REF_N
ONE_NN = 1 << F_NN


@dataclass(frozen=True)
class Fx:
    """A constant: value = m * 2^-frac."""

    m: int
    frac: int
    value: float              # the float it stands for (for the tables and the docs)

    def shift(self, f_in: int, f_out: int) -> int:
        return self.frac + f_in - f_out


def fx(v: float, f_in: int, f_out: int, headroom_bits: int = 0) -> Fx:
    """The constant ``v`` for products from format f_in to f_out: as many fractional bits as
    fit an int32, with the product's shift in [0, 62]."""
    v = float(v)
    lo = max(0, f_out - f_in)
    hi = min(46, 62 - f_in + f_out)
    f = best_frac(v, lo, hi, headroom_bits)
    return Fx(to_fixed(v, f), f, v)


def fx_at(v: float, frac: int) -> Fx:
    return Fx(to_fixed(float(v), frac), frac, float(v))


@dataclass(frozen=True)
class FxTables:
    n_meas: int
    adc_off: tuple            # 4 x Fx at the signal formats (ADC_FRAC)
    adc_lsb: tuple            # 4 x Fx (counts -> signal)
    phi: tuple                # 25 x Fx, row-major
    gamma: tuple              # 5 x Fx (force -> state)
    h: tuple                  # m*5 x Fx (state -> measurement)
    d: tuple                  # m x Fx (force -> measurement)
    k_frac: tuple             # m*5 fractional bits of the handed-over gain K (row-major 5 x m)
    bias_adaptive: bool
    kf_eta: Fx                # current -> force, motoring
    kf_over_eta: Fx           # current -> force, back-driven
    inv_eta_kf: Fx            # force -> current
    eta_over_kf: Fx
    friction: Fx              # vel -> force
    current_limit: Fx         # F_CUR
    inv_mass: Fx              # force -> acc: 1/ms + 1/mt
    cur_a: Fx                 # current -> current
    inv_cur_b: Fx             # current -> voltage
    cur_ki: Fx                # current -> voltage
    integ_limit: Fx           # F_VOLT
    kf_dt: Fx                 # acc -> voltage
    kf: Fx                    # vel -> voltage
    half_dt: Fx               # acc -> vel
    v_bus: Fx                 # F_VOLT
    v_storage: Fx
    duty_per_v_bus: Fx        # voltage -> duty counts (frac 0)
    duty_per_v_storage: Fx
    regen_min_ratio: Fx       # voltage -> voltage
    k_safety: tuple           # 5 x Fx state -> force
    k_comprehensive: tuple
    skyhook_c: Fx             # vel -> force
    skyhook_passive_c: Fx
    regen_c: Fx
    regen_skyhook_c: Fx
    force_limit: Fx           # F_FORCE
    f_kp: int                 # formats of the PID gains (plain and network-tuned)
    f_ki: int
    f_kd: int
    pid_kp: Fx                # at f_kp
    pid_ki: Fx
    pid_kd: Fx
    pid_leak: Fx              # force -> force
    dt: Fx                    # acc -> vel
    inv_dt: Fx                # acc -> jerk
    bp_w_hidden: tuple        # 20 x Fx at F_W (5 x 4)
    bp_b_hidden: tuple        # 5
    bp_w_out: tuple           # 15 (3 x 5)
    bp_b_out: tuple           # 3
    bp_eta: Fx                # delta -> delta
    bp_alpha: Fx              # weight -> weight
    bp_scale: tuple           # 3 x Fx nn -> gain formats
    bp_inv_input_scale: Fx    # acc -> nn
    bp_du_scale: tuple        # 3 x Fx: scale_l / FORCE_REF_N, du/dK_l (acc, vel, jerk) -> nn
    tanh_lut: tuple           # TANH_N + 1 ints at F_TANH
    ramp_ticks: int
    controllers: tuple


def steady_gains(p: EcuParams, road_intensity: float, ticks: int = 3000) -> np.ndarray:
    """The Kalman gain after ``ticks`` of the covariance recursion with the a-priori R."""
    a = p.akf
    P = a.p0.copy()
    K = np.zeros((5, a.H.shape[0]))
    for _ in range(ticks):
        P = a.phi @ P @ a.phi.T + road_intensity * a.q_unit
        S = a.H @ P @ a.H.T + a.r0
        K = np.linalg.solve(S, a.H @ P).T
        P = P - K @ a.H @ P
        P = 0.5 * (P + P.T)
    return K


def gain_formats(p: EcuParams) -> tuple:
    """Fractional bits of each element of K: from the largest magnitude the gain takes at the
    start (P0, R0) and in steady state at 2 and 40 m/s on roads of 0.5 G_q,A .. nominal,
    with GAIN_HEADROOM_BITS to spare (R-hat adapts); saturations are counted."""
    a = p.akf
    m = a.H.shape[0]
    S0 = a.H @ a.p0 @ a.H.T + a.r0
    ks = [np.linalg.solve(S0, a.H @ a.p0).T]
    lo = p.grade.gq_centres[0] * 0.5 / p.akf_q_gq_nominal
    for speed in (2.0, 40.0):
        for scale in (lo, 1.0):
            ks.append(steady_gains(p, a.road_intensity_per_mps * speed * scale))
    kmax = np.max(np.abs(np.array(ks)), axis=0)
    return tuple(best_frac(float(kmax[i, j]), max(0, STATE_FRAC[i] - MEAS_FRAC[j]),
                           min(46, 62 - MEAS_FRAC[j] + STATE_FRAC[i]), GAIN_HEADROOM_BITS)
                 for i in range(5) for j in range(m))


def tanh_lut() -> tuple:
    x = np.arange(TANH_N + 1) / float(1 << TANH_STEP_BITS)
    return tuple(to_fixed(float(t), F_TANH) for t in np.tanh(x))


def build_tables(p: EcuParams) -> FxTables:
    pl, c, act, a = p.plant, p.control, p.actuator, p.akf
    m = a.H.shape[0]
    chans = (p.adc.body_accel, p.adc.wheel_accel, p.adc.susp_defl, p.adc.motor_current)
    eta, kf = pl.efficiency, pl.force_constant
    f_kp = best_frac(max(abs(c.pid_kp), c.bp_scale[0]), 0, 46, 1)
    f_ki = best_frac(max(abs(c.pid_ki), c.bp_scale[1]), 0, 46, 1)
    f_kd = best_frac(max(abs(c.pid_kd), c.bp_scale[2]), 0, 46, 1)
    gain_f = (f_kp, f_ki, f_kd)
    du_f = (F_ACC, F_VEL, F_JERK)
    return FxTables(
        n_meas=m,
        adc_off=tuple(fx_at(ch.range_min, f) for ch, f in zip(chans, ADC_FRAC)),
        adc_lsb=tuple(fx(ch.lsb, 0, f) for ch, f in zip(chans, ADC_FRAC)),
        phi=tuple(fx(a.phi[i, j], STATE_FRAC[j], STATE_FRAC[i]) for i in range(5) for j in range(5)),
        gamma=tuple(fx(a.gamma[i], F_FORCE, STATE_FRAC[i]) for i in range(5)),
        h=tuple(fx(a.H[i, j], STATE_FRAC[j], MEAS_FRAC[i]) for i in range(m) for j in range(5)),
        d=tuple(fx(a.D[i], F_FORCE, MEAS_FRAC[i]) for i in range(m)),
        k_frac=gain_formats(p), bias_adaptive=bool(a.bias_adaptive),
        kf_eta=fx(kf * eta, F_CUR, F_FORCE), kf_over_eta=fx(kf / eta, F_CUR, F_FORCE),
        inv_eta_kf=fx(1.0 / (eta * kf), F_FORCE, F_CUR), eta_over_kf=fx(eta / kf, F_FORCE, F_CUR),
        friction=fx(pl.friction, F_VEL, F_FORCE),
        current_limit=fx_at(0.95 * pl.current_limit, F_CUR),   # firmware.actuator.CURRENT_MARGIN
        inv_mass=fx(1.0 / pl.ms + 1.0 / pl.mt, F_FORCE, F_ACC),
        cur_a=fx(act.current_a, F_CUR, F_CUR), inv_cur_b=fx(1.0 / act.current_b, F_CUR, F_VOLT),
        cur_ki=fx(act.ki, F_CUR, F_VOLT), integ_limit=fx_at(act.integ_limit, F_VOLT),
        kf_dt=fx(kf * p.dt_s, F_ACC, F_VOLT), kf=fx(kf, F_VEL, F_VOLT),
        half_dt=fx(0.5 * p.dt_s, F_ACC, F_VEL),
        v_bus=fx_at(pl.bus_voltage, F_VOLT), v_storage=fx_at(pl.storage_voltage, F_VOLT),
        duty_per_v_bus=fx(32768.0 / pl.bus_voltage, F_VOLT, 0),
        duty_per_v_storage=fx(32768.0 / pl.storage_voltage, F_VOLT, 0),
        regen_min_ratio=fx(c.regen_min_voltage_ratio, F_VOLT, F_VOLT),
        k_safety=tuple(fx(c.k_safety[j], STATE_FRAC[j], F_FORCE) for j in range(5)),
        k_comprehensive=tuple(fx(c.k_comprehensive[j], STATE_FRAC[j], F_FORCE) for j in range(5)),
        skyhook_c=fx(c.skyhook_c, F_VEL, F_FORCE),
        skyhook_passive_c=fx(c.skyhook_passive_c, F_VEL, F_FORCE),
        regen_c=fx(c.regen_c, F_VEL, F_FORCE), regen_skyhook_c=fx(c.regen_skyhook_c, F_VEL, F_FORCE),
        force_limit=fx_at(c.force_limit, F_FORCE),
        f_kp=f_kp, f_ki=f_ki, f_kd=f_kd,
        pid_kp=fx_at(c.pid_kp, f_kp), pid_ki=fx_at(c.pid_ki, f_ki), pid_kd=fx_at(c.pid_kd, f_kd),
        pid_leak=fx(c.pid_leak, F_FORCE, F_FORCE),
        dt=fx(p.dt_s, F_ACC, F_VEL), inv_dt=fx(1.0 / p.dt_s, F_ACC, F_JERK),
        bp_w_hidden=tuple(fx_at(w, F_W) for w in c.bp_w_hidden.ravel()),
        bp_b_hidden=tuple(fx_at(w, F_W) for w in c.bp_b_hidden),
        bp_w_out=tuple(fx_at(w, F_W) for w in c.bp_w_out.ravel()),
        bp_b_out=tuple(fx_at(w, F_W) for w in c.bp_b_out),
        bp_eta=fx(c.bp_eta, F_W, F_W), bp_alpha=fx(c.bp_alpha, F_W, F_W),
        bp_scale=tuple(fx(c.bp_scale[k], F_NN, gain_f[k]) for k in range(3)),
        bp_inv_input_scale=fx(1.0 / c.bp_input_scale, F_ACC, F_NN),
        bp_du_scale=tuple(fx(c.bp_scale[k] / FORCE_REF_N, du_f[k], F_NN) for k in range(3)),
        tanh_lut=tanh_lut(),
        ramp_ticks=p.modes.ramp_ticks, controllers=tuple(p.modes.controllers))


# ---------------------------------------------------------------- state


@dataclass
class FxPid:
    e1: int = 0
    e2: int = 0
    u: int = 0


@dataclass
class FxState:
    x: list = field(default_factory=lambda: [0] * 5)
    resid: list = field(default_factory=lambda: [0] * 3)
    ba: int = 0
    wa: int = 0
    defl: int = 0
    cur: int = 0
    force_meas: int = 0
    force_meas_prev: int = 0
    # control
    ctrl: int = CTRL_NONE
    ctrl_from: int = CTRL_NONE
    ramp: int = 0
    pid: FxPid = field(default_factory=FxPid)
    bp_pid: FxPid = field(default_factory=FxPid)
    w_h: list = field(default_factory=list)
    b_h: list = field(default_factory=list)
    w_o: list = field(default_factory=list)
    b_o: list = field(default_factory=list)
    dw_h: list = field(default_factory=lambda: [0] * 20)
    db_h: list = field(default_factory=lambda: [0] * 5)
    dw_o: list = field(default_factory=lambda: [0] * 15)
    db_o: list = field(default_factory=lambda: [0] * 3)
    gains: list = field(default_factory=lambda: [0] * 3)
    # actuator
    integ: int = 0
    i_ref_prev: int = 0
    voltage: int = 0
    i_prev: int = 0
    observer_valid: bool = False
    force: int = 0
    duty: int = 0
    gain_saturations: int = 0


def init(T: FxTables, initial_ctrl: int) -> FxState:
    s = FxState(ctrl=initial_ctrl)
    s.w_h = [w.m for w in T.bp_w_hidden]
    s.b_h = [w.m for w in T.bp_b_hidden]
    s.w_o = [w.m for w in T.bp_w_out]
    s.b_o = [w.m for w in T.bp_b_out]
    return s


def reset_estimate(s: FxState) -> None:
    s.x = [0] * 5


def _m(c: Fx, x: int, f_in: int, f_out: int) -> int:
    return mul(c.m, x, c.frac + f_in - f_out)


def _same_sign_or_zero(a: int, b: int) -> bool:
    """a * b >= 0"""
    return a == 0 or b == 0 or (a > 0) == (b > 0)


# ---------------------------------------------------------------- 1. measure


def adc_signal(T: FxTables, k: int, counts: int | None) -> int:
    if counts is None:
        return 0
    return add(T.adc_off[k].m, _m(T.adc_lsb[k], counts, 0, ADC_FRAC[k]))


def measure(T: FxTables, s: FxState, counts: tuple) -> list:
    """ADC counts (body accel, wheel accel, deflection, current; None = no good sample yet)
    -> signals; prediction of x with the force that acted over the last tick; the residual."""
    s.ba, s.wa, s.defl, s.cur = (adc_signal(T, k, counts[k]) for k in range(4))
    x = s.x
    rel_prev = sub(x[0], x[1])
    g = T.kf_eta if _same_sign_or_zero(s.cur, rel_prev) else T.kf_over_eta
    s.force_meas = _m(g, s.cur, F_CUR, F_FORCE)
    u = sat32(rshift_round(s.force_meas_prev + s.force_meas, 1))
    s.force_meas_prev = s.force_meas
    phi, gamma = T.phi, T.gamma
    xp = []
    for i in range(5):
        acc = _m(gamma[i], u, F_FORCE, STATE_FRAC[i])
        for j in range(5):
            acc += _m(phi[5 * i + j], x[j], STATE_FRAC[j], STATE_FRAC[i])
        xp.append(sat32(acc))
    s.x = xp
    z = (s.ba, s.defl, s.wa)
    resid = []
    for i in range(T.n_meas):
        acc = z[i] - _m(T.d[i], s.force_meas, F_FORCE, MEAS_FRAC[i])
        for j in range(5):
            acc -= _m(T.h[5 * i + j], xp[j], STATE_FRAC[j], MEAS_FRAC[i])
        resid.append(sat32(acc))
    s.resid = resid
    return resid


# ---------------------------------------------------------------- 3. correct


def quantize_gain(T: FxTables, s: FxState, K: np.ndarray) -> list:
    """The float gain K (5 x m) as Q numbers in the table's formats (counts saturations)."""
    out = []
    for idx, f in enumerate(T.k_frac):
        v = float(K.flat[idx])
        # a non-finite gain (diverged covariance) hands over 0: the ECU sees the non-finite
        # covariance in the same tick, flags FAULT_NONFINITE_ESTIMATE and resets the filter
        q = to_fixed(v, f) if math.isfinite(v) else 0
        if q == INT32_MAX or q == INT32_MIN:
            s.gain_saturations += 1
        out.append(q)
    return out


def correct(T: FxTables, s: FxState, k_q: list, r_q: list) -> None:
    m = T.n_meas
    eps = [sub(s.resid[j], r_q[j]) if T.bias_adaptive else s.resid[j] for j in range(m)]
    x = s.x
    for i in range(5):
        acc = x[i]
        for j in range(m):
            acc += mul(k_q[m * i + j], eps[j], T.k_frac[m * i + j] + MEAS_FRAC[j] - STATE_FRAC[i])
        x[i] = sat32(acc)


# ---------------------------------------------------------------- 5. control


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


def pid_step(T: FxTables, st: FxPid, e: int, kp: int, ki: int, kd: int) -> tuple:
    """Incremental PID (firmware.control.pid) with gains in the table's formats; returns
    (u, tp, ti, td) with the increments du/dK."""
    tp = sub(e, st.e1)
    ti = _m(T.dt, e, F_ACC, F_VEL)
    td = _m(T.inv_dt, sat32(e - 2 * st.e1 + st.e2), F_ACC, F_JERK)
    u = (_m(T.pid_leak, st.u, F_FORCE, F_FORCE) + mul(kp, tp, T.f_kp + F_ACC - F_FORCE)
         + mul(ki, ti, T.f_ki + F_VEL - F_FORCE) + mul(kd, td, T.f_kd + F_JERK - F_FORCE))
    lim = T.force_limit.m
    st.u = clamp(sat32(u), -lim, lim)
    st.e2, st.e1 = st.e1, e
    return st.u, tp, ti, td


def bppid_step(T: FxTables, s: FxState) -> int:
    y = _m(T.bp_inv_input_scale, s.ba, F_ACC, F_NN)
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
    s.gains = [_m(T.bp_scale[k], g[k], F_NN, gf[k]) for k in range(3)]
    u, tp, ti, td = pid_step(T, s.bp_pid, neg(s.ba), *s.gains)
    # learning (firmware.control.bppid): deltas and weight steps in Q(F_W)
    du = (tp, ti, td)
    du_f = (F_ACC, F_VEL, F_JERK)
    d_o = []
    for k in range(3):
        a_k = _m(T.bp_du_scale[k], du[k], du_f[k], F_NN)
        gp = mul(g[k], ONE_NN - g[k], F_NN - 1)               # g' = 2 g (1 - g)
        d_o.append(mul(mul(e, a_k, F_NN), gp, 2 * F_NN - F_W))
    d_h = []
    for i in range(5):
        back = sat32(sum(mul(s.w_o[5 * k + i], d_o[k], F_W) for k in range(3)))
        one_m_h2 = ONE_NN - mul(h[i], h[i], F_NN)
        d_h.append(mul(one_m_h2, back, F_NN))
    _learn_layer(T, s.w_o, s.dw_o, s.b_o, s.db_o, d_o, h)
    _learn_layer(T, s.w_h, s.dw_h, s.b_h, s.db_h, d_h, xin)
    return u


def _learn_layer(T: FxTables, w: list, dw: list, b: list, db: list, deltas: list,
                 inputs: tuple | list) -> None:
    """Gradient step with momentum of one layer (row-major weights, one row per delta):
    dw = alpha dw + eta delta input, db = alpha db + eta delta; w += dw, b += db."""
    n_in = len(inputs)
    for r, delta in enumerate(deltas):
        ed = _m(T.bp_eta, delta, F_W, F_W)
        for j in range(n_in):
            n = n_in * r + j
            dw[n] = add(_m(T.bp_alpha, dw[n], F_W, F_W), mul(ed, inputs[j], F_NN))
            w[n] = add(w[n], dw[n])
        db[r] = add(_m(T.bp_alpha, db[r], F_W, F_W), ed)
        b[r] = add(b[r], db[r])


def _dot_state(ks: tuple, x: list) -> int:
    return sat32(sum(_m(ks[j], x[j], STATE_FRAC[j], F_FORCE) for j in range(5)))


def force_of(T: FxTables, s: FxState, ctrl: int) -> int:
    x = s.x
    if ctrl == CTRL_LQR:
        return neg(_dot_state(T.k_safety, x))
    if ctrl == CTRL_GALQR:
        return neg(_dot_state(T.k_comprehensive, x))
    if ctrl == CTRL_SKYHOOK:
        return neg(sat32(_m(T.skyhook_c, x[0], F_VEL, F_FORCE)
                         + _m(T.skyhook_passive_c, sub(x[0], x[1]), F_VEL, F_FORCE)))
    if ctrl == CTRL_PID:
        return pid_step(T, s.pid, neg(s.ba), T.pid_kp.m, T.pid_ki.m, T.pid_kd.m)[0]
    if ctrl == CTRL_BPPID:
        return bppid_step(T, s)
    if ctrl == CTRL_REGEN:
        rel = sub(x[0], x[1])
        f = neg(sat32(_m(T.regen_c, rel, F_VEL, F_FORCE) + _m(T.regen_skyhook_c, x[0], F_VEL, F_FORCE)))
        return 0 if (f > 0 and rel > 0) or (f < 0 and rel < 0) else f
    return 0


def current_reference(T: FxTables, force: int, rel: int, compensate: bool) -> int:
    demand = add(force, _m(T.friction, rel, F_VEL, F_FORCE)) if compensate else force
    g = T.inv_eta_kf if _same_sign_or_zero(demand, rel) else T.eta_over_kf
    lim = T.current_limit.m
    return clamp(_m(g, demand, F_FORCE, F_CUR), -lim, lim)


def actuator_step(T: FxTables, s: FxState, i_ref: int, rel: int, regen: bool, rel_acc: int) -> int:
    i_meas = s.cur
    if s.observer_valid:
        emf = sub(s.voltage, _m(T.inv_cur_b, sub(i_meas, _m(T.cur_a, s.i_prev, F_CUR, F_CUR)),
                                F_CUR, F_VOLT))
        emf = add(emf, _m(T.kf_dt, rel_acc, F_ACC, F_VOLT))
    else:
        emf = _m(T.kf, add(rel, _m(T.half_dt, rel_acc, F_ACC, F_VEL)), F_VEL, F_VOLT)
    v_dc, per_v = (T.v_storage.m, T.duty_per_v_storage) if regen else (T.v_bus.m, T.duty_per_v_bus)
    v_ff = add(emf, _m(T.inv_cur_b, sub(i_ref, _m(T.cur_a, i_meas, F_CUR, F_CUR)), F_CUR, F_VOLT))
    v = add(v_ff, s.integ)
    lo, hi = -v_dc, v_dc
    if regen:
        r = _m(T.regen_min_ratio, emf, F_VOLT, F_VOLT)
        a, b = (r, emf) if r <= emf else (emf, r)
        lo, hi = max(lo, a), min(hi, b)
    saturated = v < lo or v > hi
    v = min(hi, max(lo, v))
    if not saturated:
        il = T.integ_limit.m
        s.integ = clamp(add(s.integ, _m(T.cur_ki, sub(s.i_ref_prev, i_meas), F_CUR, F_VOLT)), -il, il)
    s.i_ref_prev = i_ref
    duty = sat16(rshift_round(v * per_v.m, per_v.frac + F_VOLT))
    s.voltage = sat32(rshift_round(duty * v_dc, 15))
    s.i_prev = i_meas
    s.observer_valid = True
    return duty


def actuator_reset(s: FxState) -> None:
    s.integ = 0
    s.i_ref_prev = 0
    s.voltage = 0
    s.observer_valid = False


def control(T: FxTables, s: FxState, want: int, passive: bool, fault: bool, regen: bool) -> tuple:
    """Controller ``want`` (of the active mode) with a crossfade from the previous one; the
    actuator stage. Returns (duty_q15, enable, force Q(F_FORCE))."""
    if want != s.ctrl:
        s.ctrl_from, s.ctrl, s.ramp = s.ctrl, want, 0
        if want == CTRL_PID:
            s.pid.u = 0
        elif want == CTRL_BPPID:
            s.bp_pid.u = 0
    force = force_of(T, s, s.ctrl)
    n = T.ramp_ticks
    if s.ramp < n:
        s.ramp += 1
        f_from = force_of(T, s, s.ctrl_from)
        force = sat32(div_round(s.ramp * force + (n - s.ramp) * f_from, n))
    lim = T.force_limit.m
    force = clamp(force, -lim, lim)
    active = (not passive or s.ramp < n) and not fault
    if active:
        x = s.x
        rel = sub(x[0], x[1])
        i_ref = current_reference(T, force, rel, not regen)
        rel_acc = add(sub(s.ba, s.wa), _m(T.inv_mass, sub(force, s.force_meas), F_FORCE, F_ACC))
        duty = actuator_step(T, s, i_ref, rel, regen, rel_acc)
    else:
        actuator_reset(s)
        duty, force = 0, 0
    s.force, s.duty = force, duty
    return duty, active, force


# ---------------------------------------------------------------- one tick, for replay


@dataclass(frozen=True)
class TickIn:
    """Everything the fixed-point path takes in one tick (a line of the parity trace)."""

    counts: tuple         # 4 x int or None
    k_q: tuple            # 5*m gain mantissas
    r_q: tuple            # m bias mantissas
    want: int
    passive: bool
    fault: bool
    regen: bool
    reset: bool = False   # the float supervisor reset the estimate (non-finite covariance)


def outputs(s: FxState) -> tuple:
    """The integers compared with C on every tick."""
    return (s.duty, s.force, *s.x, *s.resid, s.integ, s.voltage)


def tick(T: FxTables, s: FxState, inp: TickIn) -> tuple:
    """measure, correct and control in one call, with the gain taken from the input."""
    measure(T, s, inp.counts)
    correct(T, s, list(inp.k_q), list(inp.r_q))
    if inp.reset:
        reset_estimate(s)
    control(T, s, inp.want, inp.passive, inp.fault, inp.regen)
    return outputs(s)
