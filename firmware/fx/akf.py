"""The fixed-point Kalman filter's integer half (C: ``fx_measure``, ``fx_correct``): ADC counts
to Q signals, the measured force, the prediction x = Phi x + Gamma u, the residual
z - H x_pred - D u, and the correction x += K (residual - r) with the gain the float
estimator hands over (``quantize_gain``), as a background task hands its result to the
control interrupt."""

from __future__ import annotations

import math

import numpy as np

from firmware.fixedpoint import (INT32_MAX, INT32_MIN, add, mul, neg, rshift_round,
                                 same_sign_or_zero, sat32, sub, to_fixed)
from firmware.fx.state import FxState
from firmware.fx.tables import (ADC_FRAC, F_CUR, F_FORCE, F_POS, MEAS_FRAC, STATE_FRAC, FxTables,
                                cm)


def adc_signal(T: FxTables, k: int, counts: int | None) -> int:
    """C: ``adc_signal``."""
    if counts is None:
        return 0
    return add(T.adc_off[k].m, cm(T.adc_lsb[k], counts, 0, ADC_FRAC[k]))


def measure(T: FxTables, s: FxState, counts: tuple) -> list:
    """ADC counts (body accel, wheel accel, deflection, current; None = no good sample yet)
    -> signals; prediction of x with the force that acted over the last tick; the residual.
    C: ``fx_measure``."""
    s.ba, s.wa, s.defl, s.cur = (adc_signal(T, k, counts[k]) for k in range(4))
    x = s.x
    rel_prev = sub(x[0], x[1])
    g = T.kf_eta if same_sign_or_zero(s.cur, rel_prev) else T.kf_over_eta
    s.force_meas = cm(g, s.cur, F_CUR, F_FORCE)
    known = add(s.force_meas, bump_force(T, s.defl))      # the actuator's and the bump stops'
    u = sat32(rshift_round(s.force_known_prev + known, 1))
    s.force_known_prev = known
    phi, gamma = T.phi, T.gamma
    xp = []
    for i in range(5):
        acc = cm(gamma[i], u, F_FORCE, STATE_FRAC[i])
        for j in range(5):
            acc += cm(phi[5 * i + j], x[j], STATE_FRAC[j], STATE_FRAC[i])
        xp.append(sat32(acc))
    s.x = xp
    z = (s.ba, s.defl, s.wa)
    resid = []
    for i in range(T.n_meas):
        acc = z[i] - cm(T.d[i], known, F_FORCE, MEAS_FRAC[i])
        for j in range(5):
            acc -= cm(T.h[5 * i + j], xp[j], STATE_FRAC[j], MEAS_FRAC[i])
        resid.append(sat32(acc))
    s.resid = resid
    return resid


def bump_force(T: FxTables, defl: int) -> int:
    """The bump stops' force on the body at the stroke ``defl`` (``firmware.akf.bump_force``;
    C: ``bump_force``)."""
    if T.bump_k.m == 0:
        return 0
    if defl > T.bump_clear.m:
        return neg(cm(T.bump_k, sub(defl, T.bump_clear.m), F_POS, F_FORCE))
    if defl < -T.bump_clear.m:
        return neg(cm(T.bump_k, add(defl, T.bump_clear.m), F_POS, F_FORCE))
    return 0


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
    """x += K (residual - r). C: ``fx_correct``."""
    m = T.n_meas
    eps = [sub(s.resid[j], r_q[j]) if T.bias_adaptive else s.resid[j] for j in range(m)]
    x = s.x
    for i in range(5):
        acc = x[i]
        for j in range(m):
            acc += mul(k_q[m * i + j], eps[j], T.k_frac[m * i + j] + MEAS_FRAC[j] - STATE_FRAC[i])
        x[i] = sat32(acc)


def reset_estimate(s: FxState) -> None:
    """The float supervisor found the covariance non-finite: the estimate starts again."""
    s.x = [0] * 5
