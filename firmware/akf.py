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

Compiled (numba) over the state record's ``akf`` fields: ``estimate`` is the float path's
stage 2 (the force from the measured current, the forces off the model, ``tick``); ``tick``
predicts and corrects in one call. The arithmetic is ``firmware.kernels.akf``'s, in
filterpy's split (``predict_ws``, then ``update_ws`` exposing the innovation; ``gain_ws`` the
update's float half, which the fixed-point path calls, ``firmware.fx.estimate``).
"""

from __future__ import annotations

import math

import numpy as np

from firmware.kernels import akf as kern
from firmware.kernels import njit
from firmware import adc

SKIP_SCALE = 1e12   # a measurement not used: its noise variance this many times R_hat's

MEASURED = (adc.BA, adc.DEFL, adc.WA)     # the filter's z, in its order

# The covariance side's inputs from the rest of the ECU in one word (the fixed-point path
# records it for the C estimator, ``c/akf_cov.h``: the same bits): the measurements held
# (bits 0-2, z order), R-hat may adapt, and the forces off the model this tick (``off_model``);
# the supervisor restarted the filter (``firmware.diag.degrade.enter``).
COV_ADAPT, COV_LIFTED, COV_CURRENT_UNKNOWN, COV_STROKE_UNKNOWN, COV_RESTART = 8, 16, 32, 64, 128


def state_dtype(m: int) -> np.dtype:
    return np.dtype([
        ("x", "f8", (5,)), ("P", "f8", (5, 5)), ("R", "f8", (m, m)), ("r", "f8", (m,)),
        ("b_pow", "f8"),                   # b^(t+1)
        ("innovation", "f8", (m,)),
        ("hph", "f8", (m,)),               # diag(H P_pred H^T) of the last correction
        ("guard_hits", "i8"),              # how often the R-hat guard acted
        ("R_saved", "f8", (m, m)),         # (R-hat while a held measurement's is scaled)
        ("ws", kern.workspace_dtype(m)),   # (the tick's intermediates: nothing allocated)
    ])


@njit
def init(A, S) -> None:
    """The filter's start (and its restart after a non-finite estimate)."""
    S.x[:] = 0.0
    S.P[:, :] = A.p0
    S.R[:, :] = A.r0
    S.r[:] = 0.0
    S.b_pow = A.forgetting
    S.innovation[:] = 0.0
    S.hph[:] = 0.0
    S.guard_hits = 0


@njit
def bump_force(A, defl: float) -> float:
    """The bump stops' force on the body at the measured stroke (0 inside the clearance)."""
    if A.bump_stiffness == 0.0:
        return 0.0
    if defl > A.bump_clearance_m:
        return -A.bump_stiffness * (defl - A.bump_clearance_m)
    if defl < -A.bump_clearance_m:
        return -A.bump_stiffness * (defl + A.bump_clearance_m)
    return 0.0


@njit
def airborne(A, ms: float, mt: float, ba: float, wa: float) -> bool:
    """The tyre force measured by the accelerometers is within ``lift_sigmas`` of its noise
    from zero (or below)."""
    return A.tyre_load_n + ms * ba + mt * wa < A.lift_sigmas * A.tyre_force_sigma_n


@njit
def _add_outer(P, s2: float, g) -> None:
    """P += s2 outer(g, g), as numpy computes it (the outer product, then the scale)."""
    for i in range(5):
        for j in range(5):
            P[i, j] = P[i, j] + s2 * (g[i] * g[j])


@njit
def unknown_forces(A, S, lifted: bool, current_unknown: bool, stroke_unknown: bool) -> None:
    """Process noise for the forces the model does not know this tick (the module's doc)."""
    if lifted and A.lift_force_sigma_n > 0.0:
        _add_outer(S.P, A.lift_force_var, A.gamma_wheel)
    s2 = (A.current_force_var if current_unknown else 0.0) + (
        A.stroke_force_var if stroke_unknown else 0.0)
    if s2 > 0.0:
        _add_outer(S.P, s2, A.gamma)


@njit
def off_model(P, S, ba: float, wa: float):
    """The covariance side of a tick off the linear model (the module's doc): returns (R-hat
    may adapt, the bits of the measurements held: z indices, the ``COV_`` bits of the forces
    off the model)."""
    current_known = adc.measured(S.adc, adc.CUR)
    stroke_known = adc.measured(S.adc, adc.DEFL)
    lifted = airborne(P.akf, P.plant.ms, P.plant.mt, ba, wa) and P.akf.lift_force_sigma_n > 0
    unknown_forces(P.akf, S.akf, lifted, not current_known, not stroke_known)
    held = 0
    for j in range(3):
        if not adc.measured(S.adc, MEASURED[j]):     # (held, or clipped at a rail)
            held |= 1 << j
    held |= out_z(S)
    adapt = (current_known and stroke_known and not lifted
             and adc.measured(S.adc, adc.BA) and adc.measured(S.adc, adc.WA))
    unknown = ((COV_LIFTED if lifted else 0) | (0 if current_known else COV_CURRENT_UNKNOWN)
               | (0 if stroke_known else COV_STROKE_UNKNOWN))
    return adapt, held, unknown


@njit
def out_z(S) -> int:
    """The measurement (z bit: BA, SWS, WA) of the sensor out (``firmware.diag.degrade``),
    which the filter never corrects with (R-hat holds meanwhile: it adapts only on ticks
    where every measurement is used); 0 if none. ``S``: the ECU's state."""
    out = S.degrade.sensor
    for j in range(3):
        if out == MEASURED[j] and j < S.akf.R.shape[0]:
            return 1 << j
    return 0


@njit
def tick(A, S, u_tick: float, road_intensity: float, ba: float, defl: float, wa: float,
         u_now: float, adapt: bool, held: int) -> bool:
    """Predict and correct with z = [ba, defl(, wa)]; R-hat adapts only where ``adapt`` and
    no measurement is held; a held one's noise is SKIP_SCALE times R-hat's for this tick.
    Returns whether the new state is finite."""
    m = S.R.shape[0]
    skip = held & ((1 << m) - 1)
    if skip:
        S.R_saved[:, :] = S.R
        for j in range(m):
            if (skip >> j) & 1:
                S.R[j, j] *= SKIP_SCALE
    S.b_pow, hit, finite = kern.tick_ws(
        A.phi, A.gamma, A.q_unit, A.H, A.D, S.P, S.R, S.r, S.x, u_tick, road_intensity, ba,
        defl, wa, u_now, A.r_floor, A.r_scale, S.b_pow, A.forgetting,
        bool(A.adaptive) and adapt and not skip, bool(A.bias_adaptive), S.innovation, S.hph,
        S.ws)
    if skip:
        S.R[:, :] = S.R_saved
    S.guard_hits += hit
    return finite


@njit
def estimate(P, S, ba: float, wa: float, defl: float, i_meas: float,
             road_intensity: float):
    """The float path's stage 2: the force from the
    measured current (the direction picks the efficiency), the known force, predict and
    correct. Returns (force_meas, finite)."""
    pl = P.plant
    rel_prev = S.akf.x[0] - S.akf.x[1]
    g = pl.efficiency if i_meas * rel_prev >= 0.0 else 1.0 / pl.efficiency
    force_meas = g * pl.force_constant * i_meas
    known = force_meas + bump_force(P.akf, defl)
    adapt, held, _ = off_model(P, S, ba, wa)
    finite = tick(P.akf, S.akf, 0.5 * (S.ctl.force_known_prev + known), road_intensity, ba,
                  defl, wa, known, adapt, held)
    S.ctl.force_known_prev = known
    return force_meas, finite


@njit
def road_per_mps(P, gq: float) -> float:
    """The filter's road intensity per m/s for the process noise: the grade estimate's G_q
    once there is one, within [G_q,A / 2, the nominal] (Sage-Husa adaptation of R needs Q
    about right on smooth roads, where sensor noise matters; a larger Q on rough roads only
    adds estimation noise: measured on D roads, SWS 0.79 instead of 0.76 in comprehensive
    mode)."""
    if P.akf_q_follows_grade and math.isfinite(gq):
        lo, hi = P.grade.gq_centres[0] * 0.5, P.akf_q_gq_nominal
        g = lo if lo > gq else gq
        g = g if g < hi else hi
        return P.akf.road_intensity_per_mps * g / P.akf_q_gq_nominal
    return P.akf.road_intensity_per_mps
