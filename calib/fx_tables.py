"""The fixed-point path's constants (``firmware.fx.tables.FxTables``) from a calibration:
every constant as a mantissa with the most fractional bits that fit, chosen so that each
product's shift is in [0, 62], the Kalman gain's formats from the range the gain takes, the
tanh table. Design-time: the firmware receives the finished tables (and C the same numbers,
``tools.tables``)."""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np

from calib import cache
from firmware.fixedpoint import best_frac, to_fixed
from firmware.fx.tables import (ADC_FRAC, F_ACC, F_CUR, F_FORCE, F_JERK, F_NN, F_POS, F_TANH, F_VEL,
                                F_VOLT, F_W, GAIN_HEADROOM_BITS, MEAS_FRAC, STATE_FRAC,
                                TANH_N, TANH_STEP_BITS, Fx, FxTables)
from firmware.kernels.bppid import FORCE_REF_N
from firmware.params import EcuParams


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
    # (math.tanh, not np.tanh: numpy's is vectorised differently with and without AVX-512)
    return tuple(to_fixed(math.tanh(float(t)), F_TANH) for t in x)


def build_tables(p: EcuParams) -> FxTables:
    """The fixed-point path's constants for calibration ``p`` (kept in the design cache,
    ``calib.cache``, under the calibration's pickled bytes and the design code)."""
    return cache.cached("fx_tables", (pickle.dumps(p, protocol=5),), lambda: _build_tables(p))


_FORMATS = ("k_frac", "f_kp", "f_ki", "f_kd")


def pinned(T: FxTables, ref: FxTables) -> FxTables:
    """``T`` (the tables of a calibration written over XCP) in the formats of ``ref`` (those
    of the ECU as built, which its A2L states): every constant at ``ref``'s fractional bits,
    ``ref``'s gain formats. A ValueError names the first constant that does not fit its
    format (it would need fewer fractional bits than the ECU was built with)."""
    def pin(name, new, old):
        if isinstance(new, Fx):
            if new.frac < old.frac:
                raise ValueError(f"{name} = {new.value:g} does not fit its fixed-point format "
                                 f"(Q{old.frac}; it needs Q{new.frac})")
            return fx_at(new.value, old.frac)
        return tuple(pin(f"{name}[{i}]", n, o) for i, (n, o) in enumerate(zip(new, old)))

    changes = {}
    for f in dataclasses.fields(FxTables):
        new, old = getattr(T, f.name), getattr(ref, f.name)
        if f.name in _FORMATS:
            for i, (n, o) in enumerate(zip(np.ravel(new), np.ravel(old))):
                if n < o:
                    raise ValueError(f"{f.name}[{i}]: the new calibration needs Q{n}, the "
                                     f"ECU was built with Q{o}")
            changes[f.name] = old
        elif isinstance(new, Fx) or (isinstance(new, tuple) and new
                                     and isinstance(new[0], Fx)):
            changes[f.name] = pin(f.name, new, old)
    return dataclasses.replace(T, **changes)


def _build_tables(p: EcuParams) -> FxTables:
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
        bump_clear=fx_at(a.bump_clearance_m, F_POS), bump_k=fx(a.bump_stiffness, F_POS, F_FORCE),
        kf_eta=fx(kf * eta, F_CUR, F_FORCE), kf_over_eta=fx(kf / eta, F_CUR, F_FORCE),
        inv_eta_kf=fx(1.0 / (eta * kf), F_FORCE, F_CUR), eta_over_kf=fx(eta / kf, F_FORCE, F_CUR),
        friction=fx(pl.friction, F_VEL, F_FORCE),
        current_limit=fx_at(p.actuator.current_limit, F_CUR),
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
        k_comfort=tuple(fx(c.k_comfort[j], STATE_FRAC[j], F_FORCE) for j in range(5)),
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
        bp_gain_alpha=fx(c.bp_gain_alpha, 0, 0),
        bp_du_scale=tuple(fx(c.bp_scale[k] / FORCE_REF_N, du_f[k], F_NN) for k in range(3)),
        tanh_lut=tanh_lut(),
        ramp_ticks=p.modes.ramp_ticks, controllers=tuple(p.modes.controllers))
