"""Adaptive Kalman filter with forgetting factor (paper §3.2.1, corrected by errata 6-9).

State x = [zs_dot, zt_dot, zs, zt, zf]; the known actuator force u enters the prediction
(errata 8); measurements z = H x + D u + v. Sage-Husa noise estimation with forgetting factor b,
d_t = (1 - b) / (1 - b^(t+1)):

    eps  = z - H x_pred - D u - r_hat                     (innovation, errata 6)
    r_hat = (1 - d) r_hat + d (z - H x_pred - D u)          (Eq. 15, optional)
    R_hat = (1 - d) R_hat + d (eps eps^T - H P_pred H^T)    (Eq. 16)

R_hat can lose positive definiteness (errata 7): after every update it is symmetrised and its
eigenvalues are floored at ``r_floor`` (the guard). The update uses the Joseph form. With
adaptation off this is exactly a linear Kalman filter (tested against filterpy).

The arithmetic is in compiled kernels (``firmware.jit``): explicit loops in a fixed order, a
Jacobi eigen-decomposition for the guard, the adjugate (or Gaussian elimination) for S^-1;
no numpy/LAPACK call per tick, the same bits compiled or interpreted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware.jit import njit
from firmware.params import AkfParams


@dataclass
class AkfState:
    x: np.ndarray
    P: np.ndarray
    R: np.ndarray
    r: np.ndarray
    b_pow: float              # b^(t+1)
    innovation: np.ndarray
    guard_hits: int = 0       # how often the R-hat guard acted
    r_scale: np.ndarray | None = None   # outer(sqrt(r_floor), sqrt(r_floor)) (the guard's)


def init(params: AkfParams) -> AkfState:
    m = params.H.shape[0]
    s = np.sqrt(params.r_floor)
    return AkfState(x=np.zeros(5), P=params.p0.copy(), R=params.r0.copy(), r=np.zeros(m),
                    b_pow=params.forgetting, innovation=np.zeros(m), r_scale=np.outer(s, s))


R_CEILING = 1e8   # largest R-hat eigenvalue, in units of the floor
JACOBI_SWEEPS = 60


def guard_r(R: np.ndarray, floor: np.ndarray,
            scale: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """Symmetrise R and bound it: in coordinates scaled by sqrt(floor) (so channels of very
    different units compare), every eigenvalue is clipped into [1, R_CEILING]. The result is
    positive definite with R >= diag(floor) (to rounding, relative to the ceiling).
    Non-finite R falls back to diag(floor). ``scale``: outer(sqrt(floor), sqrt(floor)), when
    the caller has it."""
    if scale is None:
        s = np.sqrt(floor)
        scale = np.outer(s, s)
    out = np.empty_like(R, dtype=float)
    hit = _guard(np.asarray(R, dtype=float), np.asarray(floor, dtype=float), scale, out)
    return out, hit


@njit
def _guard(R, floor, scale, out):
    """guard_r into ``out``; returns whether it acted."""
    m = R.shape[0]
    total = 0.0
    for i in range(m):
        for j in range(m):
            out[i, j] = 0.5 * (R[i, j] + R[j, i])
            total += out[i, j]
    if not math.isfinite(total):          # a NaN or inf anywhere (finite R sums finite)
        for i in range(m):
            for j in range(m):
                out[i, j] = floor[i] if i == j else 0.0
        return True
    Rn = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            Rn[i, j] = out[i, j] / scale[i, j]
    if _psd_shifted(Rn):                  # (implies trace >= n; the ceiling is checked inside)
        return False
    w, V = _jacobi_eigh(Rn)
    for k in range(m):
        w[k] = min(R_CEILING, max(1.0, w[k]))
    for i in range(m):
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += V[i, k] * w[k] * V[j, k]
            out[i, j] = s * scale[i, j]
    return True


@njit
def _psd_shifted(Rn) -> bool:
    """Is Rn - I positive semi-definite with trace(Rn) <= R_CEILING? All principal minors
    >= 0 in closed form for the 2x2 and 3x3 cases the ECU has; other sizes use the
    eigenvalues."""
    n = Rn.shape[0]
    if n == 3:
        a, b, c = Rn[0, 0], Rn[0, 1], Rn[0, 2]
        e, f, i = Rn[1, 1], Rn[1, 2], Rn[2, 2]
        if a + e + i > R_CEILING:
            return False
        a, e, i = a - 1.0, e - 1.0, i - 1.0
        if a < 0.0 or e < 0.0 or i < 0.0:
            return False
        if a * e - b * b < 0.0 or a * i - c * c < 0.0 or e * i - f * f < 0.0:
            return False
        return a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c) >= 0.0
    if n == 2:
        a, b, e = Rn[0, 0], Rn[0, 1], Rn[1, 1]
        if a + e > R_CEILING:
            return False
        a, e = a - 1.0, e - 1.0
        return a >= 0.0 and e >= 0.0 and a * e - b * b >= 0.0
    tr = 0.0
    for k in range(n):
        tr += Rn[k, k]
    if not tr <= R_CEILING:
        return False
    w, _ = _jacobi_eigh(Rn)
    for k in range(n):
        if w[k] < 1.0:
            return False
    return True


@njit
def _jacobi_eigh(A):
    """Eigenvalues w and orthonormal eigenvectors V (columns) of the symmetric matrix A, by
    cyclic Jacobi rotations (A = V diag(w) V^T). For the ECU's 2x2/3x3 R-hat: a few sweeps,
    plain floats, the same bits compiled or interpreted."""
    n = A.shape[0]
    a = A.copy()
    V = np.zeros((n, n))
    for k in range(n):
        V[k, k] = 1.0
    for _ in range(JACOBI_SWEEPS):
        off = 0.0
        diag = 0.0
        for p in range(n):
            diag += a[p, p] * a[p, p]
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        if not off > 1e-36 * diag:       # converged (or nothing finite left to rotate)
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):        # A <- A J (columns p, q)
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):        # A <- J^T A (rows p, q)
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    w = np.empty(n)
    for k in range(n):
        w[k] = a[k, k]
    return w, V


@njit
def _solve_sym(S, B):
    """S^-1 B for the symmetric positive definite innovation covariance S (the guard keeps it
    well conditioned): the adjugate for 3x3 and 2x2, Gaussian elimination with partial
    pivoting otherwise (and when the determinant is not positive). A singular S gives NaN,
    which the ECU's non-finite check catches."""
    n, cols = B.shape
    out = np.empty((n, cols))
    if n == 3:
        a, b, c = S[0, 0], S[0, 1], S[0, 2]
        e, f, i = S[1, 1], S[1, 2], S[2, 2]
        A, Bc, C = e * i - f * f, c * f - b * i, b * f - c * e
        E, F, I = a * i - c * c, b * c - a * f, a * e - b * b
        det = a * A + b * Bc + c * C
        if det > 0.0 and math.isfinite(det):
            for j in range(cols):
                b0, b1, b2 = B[0, j], B[1, j], B[2, j]
                out[0, j] = (A * b0 + Bc * b1 + C * b2) / det
                out[1, j] = (Bc * b0 + E * b1 + F * b2) / det
                out[2, j] = (C * b0 + F * b1 + I * b2) / det
            return out
    elif n == 2:
        a, b, e = S[0, 0], S[0, 1], S[1, 1]
        det = a * e - b * b
        if det > 0.0 and math.isfinite(det):
            for j in range(cols):
                out[0, j] = (e * B[0, j] - b * B[1, j]) / det
                out[1, j] = (a * B[1, j] - b * B[0, j]) / det
            return out
    M = S.copy()
    for i in range(n):
        for j in range(cols):
            out[i, j] = B[i, j]
    for k in range(n):
        piv = k
        for i in range(k + 1, n):
            if abs(M[i, k]) > abs(M[piv, k]):
                piv = i
        if not abs(M[piv, k]) > 0.0:     # singular (or NaN): no solution
            out[:, :] = math.nan
            return out
        if piv != k:
            for j in range(n):
                M[k, j], M[piv, j] = M[piv, j], M[k, j]
            for j in range(cols):
                out[k, j], out[piv, j] = out[piv, j], out[k, j]
        for i in range(k + 1, n):
            f = M[i, k] / M[k, k]
            for j in range(k, n):
                M[i, j] -= f * M[k, j]
            for j in range(cols):
                out[i, j] -= f * out[k, j]
    for k in range(n - 1, -1, -1):
        for j in range(cols):
            s = out[k, j]
            for i in range(k + 1, n):
                s -= M[k, i] * out[i, j]
            out[k, j] = s / M[k, k]
    return out


@njit
def _mm(A, B):
    """A @ B, summed in index order."""
    n, m = A.shape[0], B.shape[1]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[k, j]
            out[i, j] = s
    return out


@njit
def _mmt(A, B):
    """A @ B.T, summed in index order."""
    n, m = A.shape[0], B.shape[0]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[j, k]
            out[i, j] = s
    return out


@njit
def _predict(phi, gamma, q_unit, x, P, u, q, with_x):
    """x' = phi x + gamma u (when ``with_x``), P' = phi P phi^T + q q_unit."""
    n = P.shape[0]
    xn = x.copy()
    if with_x:
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += phi[i, j] * x[j]
            xn[i] = s + gamma[i] * u
    Pn = _mmt(_mm(phi, P), phi)
    for i in range(n):
        for j in range(n):
            Pn[i, j] += q * q_unit[i, j]
    return xn, Pn


@njit
def _gain(H, P, R, r, resid, r_floor, r_scale, b_pow, b, adaptive, bias_adaptive):
    """The correction's noise adaptation, gain and Joseph-form covariance; see ``gain``.
    Returns (K, eps, P, R, r, b_pow, guard acted)."""
    m, n = H.shape
    eps = np.empty(m)
    for i in range(m):
        eps[i] = resid[i] - r[i] if bias_adaptive else resid[i]
    HP = _mm(H, P)
    HPHt = _mmt(HP, H)
    rn = r.copy()
    Rn = R.copy()
    hit = False
    if adaptive:
        d = (1.0 - b) / (1.0 - b_pow)      # b_pow = b^(t+1); d = 1 at t = 0
        b_pow *= b
        if bias_adaptive:
            for i in range(m):
                rn[i] = (1.0 - d) * r[i] + d * resid[i]
        Ra = np.empty((m, m))
        for i in range(m):
            for j in range(m):
                Ra[i, j] = (1.0 - d) * R[i, j] + d * (eps[i] * eps[j] - HPHt[i, j])
        hit = _guard(Ra, r_floor, r_scale, Rn)
    S = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            S[i, j] = HPHt[i, j] + Rn[i, j]
    Y = _solve_sym(S, HP)                  # S^-1 H P; K = P H^T S^-1 = Y^T (S symmetric)
    K = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            K[i, j] = Y[j, i]
    # Joseph form (I-KH) P (I-KH)^T + K R K^T, expanded: P - K HP - (K HP)^T + K S K^T
    KHP = _mm(K, HP)
    KSKt = _mmt(_mm(K, S), K)
    Pj = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            Pj[i, j] = P[i, j] - KHP[i, j] - KHP[j, i] + KSKt[i, j]
    Pn = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            Pn[i, j] = 0.5 * (Pj[i, j] + Pj[j, i])
    return K, eps, Pn, Rn, rn, b_pow, hit


@njit
def _update(H, D, P, R, r, x, z, u, r_floor, r_scale, b_pow, b, adaptive, bias_adaptive):
    """Residual z - H x - D u, then ``_gain`` and x += K eps. Returns (x, P, R, r, eps,
    b_pow, guard acted)."""
    m, n = H.shape
    resid = np.empty(m)
    for i in range(m):
        s = 0.0
        for k in range(n):
            s += H[i, k] * x[k]
        resid[i] = z[i] - s - D[i] * u
    K, eps, Pn, Rn, rn, b_pow, hit = _gain(H, P, R, r, resid, r_floor, r_scale, b_pow, b,
                                          adaptive, bias_adaptive)
    xn = np.empty(n)
    for i in range(n):
        s = 0.0
        for k in range(m):
            s += K[i, k] * eps[k]
        xn[i] = x[i] + s
    return xn, Pn, Rn, rn, eps, b_pow, hit


@njit
def all_finite(x, P) -> bool:
    """No NaN or inf in the state or the covariance."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return False
    for i in range(P.shape[0]):
        for j in range(P.shape[1]):
            if not math.isfinite(P[i, j]):
                return False
    return True


# The state's arrays are updated in place by the ``*_into`` kernels: returning new arrays
# from a compiled call costs about 1 us each in boxing, the larger part of a 7.8 us update.

@njit
def _predict_into(phi, gamma, q_unit, x, P, u, q, with_x):
    xn, Pn = _predict(phi, gamma, q_unit, x, P, u, q, with_x)
    x[:] = xn
    P[:, :] = Pn


@njit
def _update_into(H, D, P, R, r, x, z, u, r_floor, r_scale, b_pow, b, adaptive, bias_adaptive,
                 eps_out):
    xn, Pn, Rn, rn, eps, b_pow, hit = _update(H, D, P, R, r, x, z, u, r_floor, r_scale, b_pow,
                                              b, adaptive, bias_adaptive)
    x[:] = xn
    P[:, :] = Pn
    R[:, :] = Rn
    r[:] = rn
    eps_out[:] = eps
    return b_pow, hit


@njit
def _tick_into(phi, gamma, q_unit, H, D, P, R, r, x, u_tick, q, z0, z1, z2, u_now, r_floor,
               r_scale, b_pow, b, adaptive, bias_adaptive, eps_out):
    _predict_into(phi, gamma, q_unit, x, P, u_tick, q, True)
    z = np.empty(H.shape[0])
    z[0] = z0
    z[1] = z1
    if z.shape[0] > 2:
        z[2] = z2
    b_pow, hit = _update_into(H, D, P, R, r, x, z, u_now, r_floor, r_scale, b_pow, b, adaptive,
                              bias_adaptive, eps_out)
    return b_pow, hit, all_finite(x, P)


def tick(params: AkfParams, st: AkfState, u_tick: float, road_intensity: float, ba: float,
         defl: float, wa: float, u_now: float) -> bool:
    """``predict`` then ``update`` with z = [ba, defl] or [ba, defl, wa] (as many as H has
    rows), in one compiled call. Returns ``all_finite`` of the new state."""
    st.b_pow, hit, finite = _tick_into(
        params.phi, params.gamma, params.q_unit, params.H, params.D, st.P, st.R, st.r, st.x,
        float(u_tick), float(road_intensity), float(ba), float(defl), float(wa), float(u_now),
        params.r_floor, st.r_scale, st.b_pow, params.forgetting, params.adaptive,
        params.bias_adaptive, st.innovation)
    st.guard_hits += int(hit)
    return finite


def predict(params: AkfParams, st: AkfState, u: float, road_intensity: float) -> None:
    _predict_into(params.phi, params.gamma, params.q_unit, st.x, st.P, float(u),
                  float(road_intensity), True)


def predict_cov(params: AkfParams, st: AkfState, road_intensity: float) -> None:
    """The covariance half of the prediction (the fixed-point path predicts x itself)."""
    _predict_into(params.phi, params.gamma, params.q_unit, st.x, st.P, 0.0,
                  float(road_intensity), False)


def update(params: AkfParams, st: AkfState, z: np.ndarray, u: float) -> None:
    st.b_pow, hit = _update_into(
        params.H, params.D, st.P, st.R, st.r, st.x, np.asarray(z, dtype=float), float(u),
        params.r_floor, st.r_scale, st.b_pow, params.forgetting, params.adaptive,
        params.bias_adaptive, st.innovation)
    st.guard_hits += int(hit)


def gain(params: AkfParams, st: AkfState, resid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From the residual z - H x_pred - D u: adapt the noise estimates, compute the gain K,
    update P (Joseph form). Returns (K, eps); the state update is x += K eps."""
    K, eps, st.P, st.R, st.r, st.b_pow, hit = _gain(
        params.H, st.P, st.R, st.r, np.asarray(resid, dtype=float), params.r_floor,
        st.r_scale, st.b_pow, params.forgetting, params.adaptive, params.bias_adaptive)
    st.guard_hits += int(hit)
    st.innovation = eps
    return K, eps


def step(params: AkfParams, st: AkfState, z: np.ndarray, u_tick: float, u_now: float,
         speed_mps: float) -> None:
    """One tick: predict over the last tick with the force that acted during it (u_tick),
    then update with this tick's measurement, whose feedthrough is the force acting now."""
    predict(params, st, u_tick, params.road_intensity_per_mps * max(speed_mps, 0.0))
    update(params, st, z, u_now)
