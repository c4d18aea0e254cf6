"""Linear quarter-car model (paper Eq. (2)-(6), corrected by errata 1-3).

State ``x = [zs_dot, zt_dot, zs, zt, zf]`` (body and wheel velocity, body and wheel
displacement, road height), input the actuator force F (pushing body up and wheel down),
disturbance unit white noise w driving the road filter of Eq. (1) at constant speed.
Outputs ``y = [BA, SWS, DTD] = [zs_ddot, zs - zt, zt - zf]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import solve_continuous_lyapunov

from calib import exact
from calib.errors import ConfigError
from calib.iso8608 import DEFAULT_CUTOFF_N_PER_M, GRADE_GQ_M3, road_noise_gain
from calib.options import NOMINAL_SPEED_MPS
from calib.vehicle import GRAVITY_MPS2, VehicleConfig, VehicleParams

if TYPE_CHECKING:                       # (annotations only)
    from calib.options import DesignOptions

OUTPUTS = ("ba", "sws", "dtd")


@dataclass(frozen=True)
class LinearModel:
    A: np.ndarray  # (5, 5)
    B: np.ndarray  # (5,)   force input
    G: np.ndarray  # (5,)   white-noise input
    C: np.ndarray  # (3, 5) outputs BA, SWS, DTD
    D: np.ndarray  # (3,)   force feedthrough (BA only)


def mechanics(vp: VehicleParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """4-state mechanics ``[zs_dot, zt_dot, zs, zt]``: (A4, B_force, B_road)."""
    ms, mt = vp.sprung_mass_kg, vp.unsprung_mass_kg
    ks, cs, kt = vp.spring_stiffness_n_per_m, vp.damping_n_s_per_m, vp.tire_stiffness_n_per_m
    A4 = np.array([
        [-cs / ms, cs / ms, -ks / ms, ks / ms],
        [cs / mt, -cs / mt, ks / mt, -(ks + kt) / mt],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
    ])
    b_force = np.array([1.0 / ms, -1.0 / mt, 0.0, 0.0])
    b_road = np.array([0.0, kt / mt, 0.0, 0.0])  # errata 1: the road enters through k_t
    return A4, b_force, b_road


def linear_model(vp: VehicleParams, gq_m3: float, speed_mps: float, convention: str = "iso",
                 cutoff_n_per_m: float = DEFAULT_CUTOFF_N_PER_M) -> LinearModel:
    """The 5-state model at constant speed: road pole -2*pi*f0 with f0 = n_c*v."""
    A4, b_force, b_road = mechanics(vp)
    A = np.zeros((5, 5))
    A[:4, :4] = A4
    A[:4, 4] = b_road
    A[4, 4] = -2.0 * math.pi * cutoff_n_per_m * speed_mps
    B = np.append(b_force, 0.0)
    G = np.zeros(5)
    G[4] = road_noise_gain(gq_m3, speed_mps, convention)
    C = np.array([
        A[0],                              # BA (without the force term, see D)
        [0.0, 0.0, 1.0, -1.0, 0.0],        # SWS (errata 3)
        [0.0, 0.0, 0.0, 1.0, -1.0],        # DTD
    ])
    D = np.array([B[0], 0.0, 0.0])
    return LinearModel(A, B, G, C, D)


def state_covariance(A_cl: np.ndarray, G: np.ndarray) -> np.ndarray:
    if np.max(np.linalg.eigvals(A_cl).real) >= 0.0:
        raise ValueError("closed loop is not stable")
    P = solve_continuous_lyapunov(A_cl, -np.outer(G, G))
    return 0.5 * (P + P.T)


def output_covariance(model: LinearModel, K: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Variances of [BA, SWS, DTD] and of the force under u = -K x (passive if K is None)."""
    if K is None:
        K = np.zeros(model.A.shape[0])
    A_cl = model.A - np.outer(model.B, K)
    P = state_covariance(A_cl, model.G)
    C_cl = model.C - np.outer(model.D, K)
    var = np.einsum("ij,jk,ik->i", C_cl, P, C_cl)
    return var, float(K @ P @ K)


def twin_system(model: LinearModel, K: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The car under u = -K x and its passive twin on one road, as one system:
    (A, G, C_active, C_passive) with state [x_active, x_passive], the same white noise
    driving both road states, and [BA, SWS, DTD] of each car as C z."""
    n = model.A.shape[0]
    K = np.zeros(n) if K is None else np.asarray(K, dtype=float)
    zero = np.zeros((n, n))
    A = np.block([[model.A - np.outer(model.B, K), zero], [zero, model.A]])
    G = np.concatenate([model.G, model.G])
    C_active = np.hstack([model.C - np.outer(model.D, K), np.zeros((3, n))])
    C_passive = np.hstack([np.zeros((3, n)), model.C])
    return A, G, C_active, C_passive


def window_scatter(model: LinearModel, K: np.ndarray | None, window_s: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """How much a ratio measured on one finite drive scatters: (ratios, sigma) for [BA, SWS,
    DTD], the exact RMS ratios to passive under u = -K x and the standard deviation of the
    log of the ratio of two RMS values measured over ``window_s`` seconds, the controlled and
    the passive car driven by the same road (a segment of ``hil sim`` against its passive
    twin).

    For a stationary Gaussian output y with autocovariance R(tau), the mean of y^2 over a
    window T has variance (2/T) int R(tau)^2 dtau (T much longer than the correlation time),
    and the means of a^2 and p^2 have covariance (2/T) int R_ap(tau)^2 dtau. With
    R(tau) = c2 e^{A tau} u (u = S c1', S the joint stationary covariance),
    int_0^inf R^2 dtau = c2 X c2' where A X + X A' = -u u' (one Lyapunov equation), and to
    first order var log(rms_a / rms_p) = (V_a / a^4 + V_p / p^4 - 2 C_ap / (a^2 p^2)) / 4.

    A lightly damped body gives narrow-band, slowly varying RMS values: the default car's
    BA ratio over 60 s scatters by about 2.5 %, as much as a design's margin."""
    if not window_s > 0.0:
        raise ValueError(f"window must be positive, got {window_s}")
    A, G, C_active, C_passive = twin_system(model, K)
    S = state_covariance(A, G)

    def later(c1: np.ndarray) -> np.ndarray:
        """X with int_0^inf (c2 e^{A t} S c1')^2 dt = c2 X c2' (c1 now, c2 t later)."""
        u = S @ c1
        return solve_continuous_lyapunov(A, -np.outer(u, u))

    ratios, sigma = np.empty(3), np.empty(3)
    for i in range(3):
        ca, cp = C_active[i], C_passive[i]
        va, vp = float(ca @ S @ ca), float(cp @ S @ cp)
        xa, xp = later(ca), later(cp)
        v_a = 4.0 * float(ca @ xa @ ca) / window_s      # (2/T) x 2 int_0^inf
        v_p = 4.0 * float(cp @ xp @ cp) / window_s
        c_ap = 2.0 * float(cp @ xa @ cp + ca @ xp @ ca) / window_s
        var_log = 0.25 * (v_a / va ** 2 + v_p / vp ** 2 - 2.0 * c_ap / (va * vp))
        ratios[i] = math.sqrt(va / vp)
        sigma[i] = math.sqrt(max(var_log, 0.0))
    return ratios, sigma


def window_covariance(model: LinearModel, K: np.ndarray | None, window_s: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(ratios, cov): the exact RMS ratios to passive of [BA, SWS, DTD] under u = -K x, and
    the 3 x 3 covariance of the logs of those ratios measured over one drive of ``window_s``
    seconds against the passive twin on the same road (its diagonal is ``window_scatter``'s
    sigma squared, to rounding; the off-diagonal terms give the scatter of a sum of ratios,
    as Eq. (43)'s).

    For stationary Gaussian outputs x, y with cross-covariance R_xy(tau), the window means of
    x^2 and y^2 over T have covariance (2/T) int R_xy(tau)^2 dtau over all tau (T much longer
    than the correlation time). With R_xy(tau) = c_x e^{A tau} S c_y' for tau >= 0 (S the
    joint stationary covariance), int_0^inf R_xy^2 dtau = c_x X_y c_x' where
    A X_y + X_y A' = -u u', u = S c_y' (one Lyapunov equation per output), and to first
    order cov(log rms_x, log rms_y) = cov(mean x^2, mean y^2) / (4 E x^2 E y^2)."""
    if not window_s > 0.0:
        raise ValueError(f"window must be positive, got {window_s}")
    A, G, C_active, C_passive = twin_system(model, K)
    S = state_covariance(A, G)
    c = np.vstack([C_active, C_passive])               # outputs: 3 active, then 3 passive
    var = np.einsum("ij,jk,ik->i", c, S, c)
    X = [solve_continuous_lyapunov(A, -np.outer(S @ ci, S @ ci)) for ci in c]
    later = np.array([[float(c[i] @ X[j] @ c[i]) for j in range(6)] for i in range(6)])
    mean_cov = 2.0 * (later + later.T) / window_s       # cov of the window means of y^2
    log_cov = 0.25 * mean_cov / np.outer(var, var)      # cov of the logs of the RMS values
    D = np.hstack([np.eye(3), -np.eye(3)])              # log ratio = log rms_a - log rms_p
    return np.sqrt(var[:3] / var[3:]), D @ log_cov @ D.T


def window_bound(model: LinearModel, K: np.ndarray | None, opts: DesignOptions) -> np.ndarray:
    """exp(-z sigma) for [BA, SWS, DTD]: the exact ratio at most this keeps a ratio measured
    over a drive of ``opts.ratio_window_s`` at most 1 with ``opts.ratio_window_z`` sigma
    confidence (``window_scatter``, sigma at the gain K)."""
    _, sigma = window_scatter(model, K, opts.ratio_window_s)
    return np.exp(-opts.ratio_window_z * sigma)


def passive_psd(model: LinearModel, f_hz: np.ndarray) -> np.ndarray:
    """One-sided PSDs of [BA, SWS, DTD] of the passive car at frequencies ``f_hz``, in
    (unit)^2/Hz: 2 |C (j 2 pi f - A)^-1 G|^2 for the model's unit white noise (its
    integral over f is the variance ``output_covariance`` gives)."""
    f = np.asarray(f_hz, dtype=float)
    n = model.A.shape[0]
    out = np.empty((model.C.shape[0], f.size))
    for i, fi in enumerate(f):
        h = model.C @ np.linalg.solve(2j * math.pi * fi * np.eye(n) - model.A, model.G)
        out[:, i] = 2.0 * np.abs(h) ** 2
    return out


def passive_rms(model: LinearModel) -> np.ndarray:
    """Exact RMS of [BA (m/s^2), SWS (m), DTD (m)] of the passive car."""
    var, _ = output_covariance(model)
    return np.sqrt(var)


def van_loan_integral(M: np.ndarray, Q: np.ndarray, dt: float) -> np.ndarray:
    """W = integral_0^dt expm(M^T t) Q expm(M t) dt (Van Loan), so the integral of
    zeta^T Q zeta along zeta' = M zeta is zeta0^T W zeta0. With M = A^T and Q = G G^T it is the
    discrete process-noise covariance of x' = A x + G w over dt."""
    n = M.shape[0]
    big = np.zeros((2 * n, 2 * n))
    big[:n, :n] = -M.T
    big[:n, n:] = Q
    big[n:, n:] = M
    E = exact.expm(big * dt)
    W = exact.matmul(E[n:, n:].T, E[:n, n:])
    return np.asarray((W + W.T) / exact.LD(2.0), dtype=float)


def paper_thresholds(vp: VehicleParams, convention: str = "iso",
                     cutoff_n_per_m: float = DEFAULT_CUTOFF_N_PER_M) -> tuple[float, float, float]:
    """Eq. (24)-(26): (dtd1, ba1, ba2), the passive RMS values that bound the B and C roads
    over 10-30 m/s: DTD of grade B at 30 m/s, BA of grade B at 10 m/s, BA of grade C at 30 m/s."""
    def model(grade: str, speed: float) -> LinearModel:
        return linear_model(vp, GRADE_GQ_M3[grade], speed, convention, cutoff_n_per_m)

    return (float(passive_rms(model("B", 30.0))[2]), float(passive_rms(model("B", 10.0))[0]),
            float(passive_rms(model("C", 30.0))[0]))


MAX_MODE_DT = 0.5            # the fastest passive mode |lambda| * dt at most this (80 Hz at 1 kHz)
MAX_STATIC_DEFLECTION_M = (0.5, 0.1)   # spring, tyre under the static load
MAX_FORCE_N = 32767          # the actuator's peak force: within FORCE_CMD's range (int16 N)


def check_plausible(cfg: VehicleConfig, path) -> None:
    """Refuse, with the reason, a vehicle the bench cannot simulate or calibrate honestly:
    a passive mode too fast for the plant step (a feather-light mass, a rigid spring), a
    spring or tyre that sags more than ``MAX_STATIC_DEFLECTION_M`` under the static load, a
    static deflection from the ride height (a payload) that leaves no stroke to a stop, or an
    actuator whose peak force (force constant x current limit) leaves FORCE_CMD's int16
    range and the firmware's integer signals (so no overflow is possible downstream)."""
    vp, ap, dt = cfg.vehicle, cfg.actuator, cfg.sim.plant_dt_s
    A4 = mechanics(vp)[0]
    lam = np.linalg.eigvals(A4) if np.all(np.isfinite(A4)) else np.array([np.nan])
    if not np.all(np.isfinite(lam)):
        raise ConfigError(f"{path}: the vehicle's dynamics are not finite (check [vehicle])")
    fastest = float(np.max(np.abs(lam)))
    if fastest * dt > MAX_MODE_DT:
        raise ConfigError(
            f"{path}: the passive car's fastest mode ({fastest / (2 * math.pi):.4g} Hz) is too "
            f"fast for the plant step of {dt:g} s (at most "
            f"{MAX_MODE_DT / dt / (2 * math.pi):.3g} Hz): check the masses and stiffnesses")
    sag = (vp.sprung_mass_kg * GRAVITY_MPS2 / vp.spring_stiffness_n_per_m,
           vp.static_tire_load_n / vp.tire_stiffness_n_per_m)
    for what, value, limit in zip(("spring_stiffness_n_per_m", "tire_stiffness_n_per_m"),
                                  sag, MAX_STATIC_DEFLECTION_M):
        if value > limit:
            raise ConfigError(f"{path}: vehicle.{what} sags {value:.3g} m under the static "
                              f"load (at most {limit:g} m)")
    nl = cfg.nonlinear
    if abs(nl.static_deflection_m) >= nl.bump_stop_clearance_m:
        raise ConfigError(f"{path}: the static deflection ({1e3 * nl.static_deflection_m:+.1f} "
                          f"mm from the ride height) leaves no stroke to the bump stop "
                          f"({1e3 * nl.bump_stop_clearance_m:g} mm)")
    peak = ap.force_constant_n_per_a * ap.current_limit_a
    if not peak <= MAX_FORCE_N:
        raise ConfigError(f"{path}: the actuator's peak force (force constant "
                          f"{ap.force_constant_n_per_a:.4g} N/A x current limit "
                          f"{ap.current_limit_a:g} A = {peak:.4g} N) exceeds {MAX_FORCE_N} N, "
                          f"FORCE_CMD's range: check screw_lead_m and torque_constant_nm_per_a")


def zoh_input(A: np.ndarray, B: np.ndarray, dt: float) -> np.ndarray:
    """The discrete input vector of x' = A x + B u with u held over dt (contiguous)."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A
    M[:n, n] = B
    return np.ascontiguousarray(exact.expm(M * dt)[:n, n])


def filter_continuous(cfg: VehicleConfig, speed: float = NOMINAL_SPEED_MPS
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The ECU filter's continuous model: (A, B_force), the 5-state quarter car with the
    screw's viscous friction beside the damper and the road pole at ``speed``."""
    vp, ap = cfg.vehicle, cfg.actuator
    A4, b_force, b_road = mechanics(vp)
    b = ap.viscous_friction_n_s_per_m
    A = np.zeros((5, 5))
    A[:4, :4] = A4
    A[0, 0] -= b / vp.sprung_mass_kg
    A[0, 1] += b / vp.sprung_mass_kg
    A[1, 0] += b / vp.unsprung_mass_kg
    A[1, 1] -= b / vp.unsprung_mass_kg
    A[:4, 4] = b_road
    A[4, 4] = -2.0 * math.pi * DEFAULT_CUTOFF_N_PER_M * speed
    return A, np.append(b_force, 0.0)


def filter_discrete(cfg: VehicleConfig, dt: float):
    """The ECU filter's model at its tick: (A, B_force, phi, gamma, q_unit), q_unit the
    discrete process noise per unit intensity of the road's white noise."""
    A, B = filter_continuous(cfg)
    e5 = np.eye(5)[4]
    return (A, B, exact.expm(A * dt), zoh_input(A, B, dt),
            van_loan_integral(A.T, np.outer(e5, e5), dt))
