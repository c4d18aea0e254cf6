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

Off the linear model (docs/ecu.md): the bump stops' force, computed from the measured stroke,
is a known input beside the actuator's (``bump_force``); an airborne tyre (``airborne``: the
measured tyre force near zero) and a current beyond its sensor's range are forces the model
does not know, added to P as process noise for that tick (``unknown_forces``); and R_hat does
not adapt on such a tick (``tick``/``gain``'s ``adapt``): its innovations say nothing about the
sensors' noise, and absorbing them made R_hat grow by 10^3-10^5 on rough roads at 30 m/s
(``hil alarms``), the estimate then drifting for seconds.

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
         defl: float, wa: float, u_now: float, adapt: bool = True, skip: tuple = ()) -> bool:
    """``predict`` then ``update`` with z = [ba, defl] or [ba, defl, wa] (as many as H has
    rows), in one compiled call; R_hat adapts only where ``adapt``; the measurements of
    ``skip`` (indices into z: held values, not measurements) are not used. Returns
    ``all_finite`` of the new state."""
    saved = _skip(st, skip)
    st.b_pow, hit, finite = kern.tick_into(
        params.phi, params.gamma, params.q_unit, params.H, params.D, st.P, st.R, st.r, st.x,
        float(u_tick), float(road_intensity), float(ba), float(defl), float(wa), float(u_now),
        params.r_floor, st.r_scale, st.b_pow, params.forgetting,
        params.adaptive and adapt and saved is None, params.bias_adaptive, st.innovation,
        st.hph)
    if saved is not None:
        st.R[:, :] = saved
    st.guard_hits += int(hit)
    return finite


SKIP_SCALE = 1e12   # a measurement not used: its noise variance this many times R_hat's


def _skip(st: AkfState, skip: tuple) -> np.ndarray | None:
    """R_hat before this tick's measurements of ``skip`` were made useless (their variance
    times SKIP_SCALE: a gain of ~1e-12 of the usual), or None when there are none."""
    skip = [j for j in skip if j < st.R.shape[0]]
    if not skip:
        return None
    saved = st.R.copy()
    for j in skip:
        st.R[j, j] *= SKIP_SCALE
    return saved


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


def gain(params: AkfParams, st: AkfState, resid: np.ndarray, adapt: bool = True,
         skip: tuple = ()) -> tuple[np.ndarray, np.ndarray]:
    """From the residual z - H x_pred - D u: adapt the noise estimates (where ``adapt``),
    compute the gain K (not using the measurements of ``skip``), update P (Joseph form).
    Returns (K, eps); the state update is x += K eps."""
    saved = _skip(st, skip)
    K, eps, st.P, st.R, st.r, st.b_pow, hit, st.hph = kern.gain(
        params.H, st.P, st.R, st.r, np.asarray(resid, dtype=float), params.r_floor,
        st.r_scale, st.b_pow, params.forgetting, params.adaptive and adapt and saved is None,
        params.bias_adaptive)
    if saved is not None:
        st.R = saved
    st.guard_hits += int(hit)
    st.innovation = eps
    return K, eps


def finite(st: AkfState) -> bool:
    """No NaN or inf in the state or the covariance."""
    return kern.all_finite(st.x, st.P)


def bump_force(params: AkfParams, defl: float) -> float:
    """The bump stops' force on the body at the measured stroke ``defl`` (the wheel takes the
    opposite, as with the actuator's): 0 inside the clearance and without bump stops."""
    if params.bump_stiffness == 0.0:
        return 0.0
    if defl > params.bump_clearance_m:
        return -params.bump_stiffness * (defl - params.bump_clearance_m)
    if defl < -params.bump_clearance_m:
        return -params.bump_stiffness * (defl + params.bump_clearance_m)
    return 0.0


def tyre_force(params: AkfParams, ms: float, mt: float, ba: float, wa: float) -> float:
    """The tyre's vertical force measured by the two accelerometers: the static load plus
    ms BA + mt WA (every other force of the corner is internal to it)."""
    return params.tyre_load_n + ms * ba + mt * wa


def airborne(params: AkfParams, ms: float, mt: float, ba: float, wa: float) -> bool:
    """The measured tyre force is within ``lift_sigmas`` of its noise from zero (or below):
    the tyre is off the road, or the linear tyre would pull."""
    return tyre_force(params, ms, mt, ba, wa) < params.lift_sigmas * params.tyre_force_sigma_n


def unknown_forces(params: AkfParams, st: AkfState, lifted: bool, current_unknown: bool,
                   stroke_unknown: bool) -> None:
    """Process noise for the forces the model does not know this tick, added to P before the
    prediction: the airborne tyre's force on the wheel (``lifted``, where the vehicle's tyre
    can lift off); the actuator's force when its current is beyond the sensor's range or the
    sensor is faulty (``current_unknown``); the bump stops' force when the stroke is
    (``stroke_unknown``: beyond the range, the stops push harder than the clipped stroke
    says)."""
    if lifted and params.lift_force_sigma_n > 0.0:
        g, s2 = params.gamma_wheel, params.lift_force_sigma_n ** 2
        st.P += s2 * np.outer(g, g)
    s2 = (params.current_force_sigma_n ** 2 if current_unknown else 0.0) + (
        params.stroke_force_sigma_n ** 2 if stroke_unknown else 0.0)
    if s2 > 0.0:
        st.P += s2 * np.outer(params.gamma, params.gamma)
