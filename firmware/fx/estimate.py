"""Stage 2 of the fixed-point path (``firmware.fx``): the integer prediction and correction
of x around the float covariance side of the Kalman filter (the forces off the model, the
prediction of P, the Sage-Husa R-hat with its guard, the gain, the Joseph update:
``firmware.akf``, ``firmware.kernels.akf``), whose gain is handed over as Q numbers.

The tick records what the covariance side took in (``fx`` state: ``q_road``, the road's
process-noise intensity, and ``cov_flags``, the ``firmware.akf.COV_`` bits) and the float gain
it gave (``k_f``), so that ``c/akf_cov.c`` can replay the covariance side from the same inputs
and must give the same gain bits (``tests/test_c_parity.py``)."""

from __future__ import annotations

import math

from firmware import akf
from firmware.fixedpoint import to_fixed, to_float
from firmware.fx import path as fx
from firmware.fx.tables import F_FORCE, MEAS_FRAC, STATE_FRAC
from firmware.kernels import akf as kern
from firmware.kernels import njit


@njit
def estimate(P, T, S, ba, wa, road_intensity):
    """Counts -> signals, x predicted (integer); P's forces off the model and prediction,
    R-hat, the gain (float); the gain quantised, x corrected (integer). Returns
    (force_meas, finite)."""
    A, F, K = P.akf, S.fx, S.akf
    m = K.R.shape[0]
    for c in range(4):           # the last good counts (-1: none yet)
        F.counts[c] = S.adc.counts[c]
    F.reset = False
    fx.measure(T, F, F.counts)
    adapt, held, unknown = akf.off_model(P, S, ba, wa)
    F.q_road = road_intensity
    F.cov_flags = held | (akf.COV_ADAPT if adapt else 0) | unknown
    kern.predict_ws(A.phi, A.gamma, A.q_unit, K.x, K.P, 0.0, road_intensity, False, K.ws)
    for j in range(m):
        r = K.r[j]
        F.r_q[j] = to_fixed(r, MEAS_FRAC[j]) if math.isfinite(r) else 0
        S.resid_f[j] = to_float(F.resid[j], MEAS_FRAC[j])
    skip = held & ((1 << m) - 1)
    if skip:
        K.R_saved[:, :] = K.R
        for j in range(m):
            if (skip >> j) & 1:
                K.R[j, j] *= akf.SKIP_SCALE
    K.b_pow, hit = kern.gain_ws(
        A.H, K.P, K.R, K.r, S.resid_f, A.r_floor, A.r_scale, K.b_pow, A.forgetting,
        bool(A.adaptive) and adapt and not skip, bool(A.bias_adaptive), K.ws)
    if skip:
        K.R[:, :] = K.R_saved
    K.hph[:] = K.ws.hph
    K.innovation[:] = K.ws.eps
    K.guard_hits += hit
    fx.quantize_gain(T, F, K.ws.K)
    fx.correct(T, F)
    for i in range(5):
        K.x[i] = to_float(F.x[i], STATE_FRAC[i])
    return to_float(F.force_meas, F_FORCE), kern.all_finite(K.x, K.P)
