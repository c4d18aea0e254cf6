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

The API is filterpy's split: ``predict`` then ``update`` (the innovation in
``AkfState.innovation``); ``tick`` is the two in one compiled call (the ECU's per-tick path, the
same arithmetic), ``gain`` the update's float half for the fixed-point path. The arithmetic is
in ``firmware.kernels.akf``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware.kernels import akf as kern
from firmware.params import AkfParams


@dataclass
class AkfState:
    x: np.ndarray
    P: np.ndarray
    R: np.ndarray
    r: np.ndarray
    b_pow: float              # b^(t+1)
    innovation: np.ndarray
    hph: np.ndarray               # diag(H P_pred H^T) of the last correction (fault detection)
    guard_hits: int = 0       # how often the R-hat guard acted
    r_scale: np.ndarray | None = None   # outer(sqrt(r_floor), sqrt(r_floor)) (the guard's)


def init(params: AkfParams) -> AkfState:
    m = params.H.shape[0]
    s = np.sqrt(params.r_floor)
    return AkfState(x=np.zeros(5), P=params.p0.copy(), R=params.r0.copy(), r=np.zeros(m),
                    b_pow=params.forgetting, innovation=np.zeros(m), hph=np.zeros(m),
                    r_scale=np.outer(s, s))


R_CEILING = kern.R_CEILING   # largest R-hat eigenvalue, in units of the floor


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
    hit = kern.guard(np.asarray(R, dtype=float), np.asarray(floor, dtype=float), scale, out)
    return out, hit


def tick(params: AkfParams, st: AkfState, u_tick: float, road_intensity: float, ba: float,
         defl: float, wa: float, u_now: float) -> bool:
    """``predict`` then ``update`` with z = [ba, defl] or [ba, defl, wa] (as many as H has
    rows), in one compiled call. Returns ``all_finite`` of the new state."""
    st.b_pow, hit, finite = kern.tick_into(
        params.phi, params.gamma, params.q_unit, params.H, params.D, st.P, st.R, st.r, st.x,
        float(u_tick), float(road_intensity), float(ba), float(defl), float(wa), float(u_now),
        params.r_floor, st.r_scale, st.b_pow, params.forgetting, params.adaptive,
        params.bias_adaptive, st.innovation, st.hph)
    st.guard_hits += int(hit)
    return finite


def predict(params: AkfParams, st: AkfState, u: float, road_intensity: float) -> None:
    kern.predict_into(params.phi, params.gamma, params.q_unit, st.x, st.P, float(u),
                  float(road_intensity), True)


def predict_cov(params: AkfParams, st: AkfState, road_intensity: float) -> None:
    """The covariance half of the prediction (the fixed-point path predicts x itself)."""
    kern.predict_into(params.phi, params.gamma, params.q_unit, st.x, st.P, 0.0,
                  float(road_intensity), False)


def update(params: AkfParams, st: AkfState, z: np.ndarray, u: float) -> None:
    st.b_pow, hit = kern.update_into(
        params.H, params.D, st.P, st.R, st.r, st.x, np.asarray(z, dtype=float), float(u),
        params.r_floor, st.r_scale, st.b_pow, params.forgetting, params.adaptive,
        params.bias_adaptive, st.innovation, st.hph)
    st.guard_hits += int(hit)


def gain(params: AkfParams, st: AkfState, resid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From the residual z - H x_pred - D u: adapt the noise estimates, compute the gain K,
    update P (Joseph form). Returns (K, eps); the state update is x += K eps."""
    K, eps, st.P, st.R, st.r, st.b_pow, hit, st.hph = kern.gain(
        params.H, st.P, st.R, st.r, np.asarray(resid, dtype=float), params.r_floor,
        st.r_scale, st.b_pow, params.forgetting, params.adaptive, params.bias_adaptive)
    st.guard_hits += int(hit)
    st.innovation = eps
    return K, eps


def finite(st: AkfState) -> bool:
    """No NaN or inf in the state or the covariance."""
    return kern.all_finite(st.x, st.P)
