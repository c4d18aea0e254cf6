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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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
    Ht: np.ndarray | None = None        # H^T, contiguous


def init(params: AkfParams) -> AkfState:
    m = params.H.shape[0]
    s = np.sqrt(params.r_floor)
    return AkfState(x=np.zeros(5), P=params.p0.copy(), R=params.r0.copy(), r=np.zeros(m),
                    b_pow=params.forgetting, innovation=np.zeros(m), r_scale=np.outer(s, s),
                    Ht=np.ascontiguousarray(params.H.T))


R_CEILING = 1e8   # largest R-hat eigenvalue, in units of the floor


def guard_r(R: np.ndarray, floor: np.ndarray,
            scale: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """Symmetrise R and bound it: in coordinates scaled by sqrt(floor) (so channels of very
    different units compare), every eigenvalue is clipped into [1, R_CEILING]. The result is
    positive definite with R >= diag(floor) (to rounding, relative to the ceiling).
    Non-finite R falls back to diag(floor). ``scale``: outer(sqrt(floor), sqrt(floor)), when
    the caller has it."""
    Rs = R + R.T
    if not math.isfinite(float(Rs.sum())):   # a NaN or inf anywhere (finite R sums finite)
        return np.diag(floor).astype(float), True
    if scale is None:
        s = np.sqrt(floor)
        scale = np.outer(s, s)
    Rs *= 0.5
    Rn = Rs / scale
    if _psd_shifted(Rn):   # (implies trace >= n; the ceiling is checked inside)
        return Rs, False
    w, V = np.linalg.eigh(Rn)
    w = np.clip(w, 1.0, R_CEILING)
    return ((V * w) @ V.T) * scale, True


def _psd_shifted(Rn: np.ndarray) -> bool:
    """Is Rn - I positive semi-definite with trace(Rn) <= R_CEILING? All principal minors
    >= 0, in plain float arithmetic for the 2x2 and 3x3 cases the ECU has (a numpy call per
    minor costs more than the filter update); other sizes use the eigenvalues."""
    n = Rn.shape[0]
    if n == 3:
        (a, b, c), (_, e, f), (_, _, i) = Rn.tolist()
        if a + e + i > R_CEILING:
            return False
        a, e, i = a - 1.0, e - 1.0, i - 1.0
        if a < 0.0 or e < 0.0 or i < 0.0:
            return False
        if a * e - b * b < 0.0 or a * i - c * c < 0.0 or e * i - f * f < 0.0:
            return False
        return a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c) >= 0.0
    if n == 2:
        (a, b), (_, e) = Rn.tolist()
        if a + e > R_CEILING:
            return False
        a, e = a - 1.0, e - 1.0
        return a >= 0.0 and e >= 0.0 and a * e - b * b >= 0.0
    return bool(np.trace(Rn) <= R_CEILING and np.linalg.eigvalsh(Rn - np.eye(n))[0] >= 0.0)


def _solve_sym(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    """S^-1 B for the symmetric positive definite innovation covariance S (the guard keeps it
    well conditioned): the adjugate in plain floats for 3x3 and 2x2, LAPACK otherwise."""
    n = S.shape[0]
    if n == 3:
        (a, b, c), (_, e, f), (_, _, i) = S.tolist()
        A, Bc, C = e * i - f * f, c * f - b * i, b * f - c * e
        E, F, I = a * i - c * c, b * c - a * f, a * e - b * b
        det = a * A + b * Bc + c * C
        if det > 0.0 and math.isfinite(det):
            return np.array(((A, Bc, C), (Bc, E, F), (C, F, I))) @ B / det
    elif n == 2:
        (a, b), (_, e) = S.tolist()
        det = a * e - b * b
        if det > 0.0 and math.isfinite(det):
            return np.array(((e, -b), (-b, a))) @ B / det
    return np.linalg.solve(S, B)


def predict(params: AkfParams, st: AkfState, u: float, road_intensity: float) -> None:
    st.x = params.phi @ st.x + params.gamma * u
    predict_cov(params, st, road_intensity)


def predict_cov(params: AkfParams, st: AkfState, road_intensity: float) -> None:
    """The covariance half of the prediction (the fixed-point path predicts x itself)."""
    st.P = params.phi @ st.P @ params.phi.T + road_intensity * params.q_unit


def update(params: AkfParams, st: AkfState, z: np.ndarray, u: float) -> None:
    resid = z - params.H @ st.x - params.D * u
    K, eps = gain(params, st, resid)
    st.x = st.x + K @ eps


def gain(params: AkfParams, st: AkfState, resid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From the residual z - H x_pred - D u: adapt the noise estimates, compute the gain K,
    update P (Joseph form). Returns (K, eps); the state update is x += K eps."""
    H, Ht = params.H, st.Ht
    eps = resid - st.r if params.bias_adaptive else resid
    HP = H @ st.P
    HPHt = HP @ Ht
    if params.adaptive:
        b = params.forgetting
        d = (1.0 - b) / (1.0 - st.b_pow)   # b_pow = b^(t+1); d = 1 at t = 0
        st.b_pow *= b
        if params.bias_adaptive:
            st.r = (1.0 - d) * st.r + d * resid
        R = (1.0 - d) * st.R + d * (eps[:, None] * eps - HPHt)
        st.R, hit = guard_r(R, params.r_floor, st.r_scale)
        st.guard_hits += int(hit)
    S = HPHt + st.R
    K = _solve_sym(S, HP).T                 # P H^T S^-1  (S symmetric)
    # Joseph form (I-KH) P (I-KH)^T + K R K^T, expanded: P - K HP - (K HP)^T + K S K^T
    KHP = K @ HP
    P = st.P - KHP - KHP.T + K @ S @ K.T
    P += P.T
    P *= 0.5
    st.P = P
    st.innovation = eps
    return K, eps


def step(params: AkfParams, st: AkfState, z: np.ndarray, u_tick: float, u_now: float,
         speed_mps: float) -> None:
    """One tick: predict over the last tick with the force that acted during it (u_tick),
    then update with this tick's measurement, whose feedthrough is the force acting now."""
    predict(params, st, u_tick, params.road_intensity_per_mps * max(speed_mps, 0.0))
    update(params, st, z, u_now)
