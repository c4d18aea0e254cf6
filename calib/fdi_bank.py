"""The isolation bank's residual generators (docs/diagnostics.md, "Isolability"): fixed-gain
Kalman filters, each blind to one sensor (the generalised observer scheme). A fault of sensor
j cannot make the filter that does not read j inconsistent; every filter that turns
inconsistent clears the sensor it is blind to, and j is isolated once all the others are.

The winding model (``_winding_model``): x = [zs_dot, zt_dot, zs, zt, zf, i, v_off], the
5-state quarter car of the ECU's filter (``calib.model.filter_continuous``: the screw's
friction, the road state) with the winding L di/dt = V + v_off - R i - K_e (zs_dot - zt_dot)
driven by the voltage the bridge applies, the force K_f i, and v_off a random walk for what
the voltage model misses (the supply's measurement, the winding's resistance, the back-EMF
constant). Two structures (``DesignOptions.fdi_bank_structure``):

* ``voltage`` (the default): all four filters on the winding model, each reading three of
  BA, SWS, WA and the current. A bridge fault (a stuck duty, an open winding) makes all
  four inconsistent: no sensor fits, and the actuator test names the actuator.
* ``force``: the ``ba``, ``wa``, ``defl`` filters take the force from the measured current
  (the ECU filter's own 5-state structure) and read two of BA, SWS, WA; only ``current`` is
  on the winding model.

``full`` reads [BA, SWS, WA] with the force from the current: the ECU's filter with its
gain fixed (the detection the analysis compares with).

Each filter's gain is the steady-state one at the design road (``DesignOptions.akf_q_grade``
at the nominal speed). Its innovation covariance at any road intensity q is then exact
without a Riccati step per tick: the error dynamics are linear in their noises, so
S(q) = q S_road + S_noise, plus var_F S_force for a white force error of variance var_F
(the screw efficiency's band, ``firmware.diag.fdi``).

Error dynamics of a filter (Phi, H, K; prediction e-, innovation nu):
e-_{t+1} = Phi (I - K H) e-_t + b f_t, nu_t = H e-_t + d f_t, for a disturbance f that
enters the state through b and the measurement through d (``fault_input`` gives them for a
sensor's fault; the force error: b = gamma - Phi K D, d = D).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib import exact, grid
from calib.iso8608 import GRADE_GQ_M3, road_intensity_per_mps
from calib.model import filter_continuous, filter_discrete, van_loan_integral, zoh_input
from calib.options import NOMINAL_SPEED_MPS, DesignOptions
from calib.vehicle import VehicleConfig

SENSORS = ("ba", "wa", "defl", "current")       # the sensors a filter can be blind to
CHANNEL = {"ba": "body_accel", "wa": "wheel_accel", "defl": "susp_defl",   # (their [sensors]
           "current": "motor_current"}                                      #  tables)
READS = {"ba": ("defl", "wa"), "wa": ("ba", "defl"), "defl": ("ba", "wa"),
         "current": ("ba", "defl", "wa"), "full": ("ba", "defl", "wa")}
# the "voltage" structure: every bank filter on the winding model, the current a measurement
READS_VOLTAGE = {"ba": ("defl", "wa", "current"), "wa": ("ba", "defl", "current"),
                 "defl": ("ba", "wa", "current"), "current": ("ba", "defl", "wa"),
                 "full": ("ba", "defl", "wa")}


@dataclass(frozen=True)
class Generator:
    """One residual generator: the filter blind to ``blind`` (``full``: to none)."""
    blind: str
    reads: tuple            # the measured channels, in the order of H's rows
    phi: np.ndarray         # (n, n)
    gamma: np.ndarray       # (n,) the known input: the force (n = 5) or the voltage (n = 7)
    gamma_force: np.ndarray  # (n,) a force error's way into the state
    H: np.ndarray           # (m, n)
    D: np.ndarray           # (m,) the known input's feedthrough (the force's; 0 for n = 7)
    D_force: np.ndarray     # (m,) a force error's feedthrough
    K: np.ndarray           # (n, m) steady-state gain at the design road
    r0: np.ndarray          # (m, m) measurement noise
    q_unit: np.ndarray      # (n, n) process noise per unit road intensity
    q_fixed: np.ndarray     # (n, n) process noise that does not scale with the road
    S_road: np.ndarray      # (m, m) innovation covariance per unit road intensity
    S_noise: np.ndarray     # (m, m) ... from the measurement and fixed process noise
    S_force: np.ndarray     # (m, m) ... per unit variance of a white force error (N^2)
    force_per_amp: float    # K_f: a current sensor's error as a force error

    @property
    def error_phi(self) -> np.ndarray:
        return self.phi @ (np.eye(self.phi.shape[0]) - self.K @ self.H)

    def innovation_cov(self, intensity: float, var_force: float = 0.0) -> np.ndarray:
        return intensity * self.S_road + self.S_noise + var_force * self.S_force

    def fault_input(self, sensor: str) -> tuple[np.ndarray, np.ndarray]:
        """(b, d): how an additive fault of ``sensor`` (in its own unit) enters this filter's
        error dynamics; zeros where the filter does not read it."""
        n, m = self.phi.shape[0], self.H.shape[0]
        if sensor in self.reads:
            e = np.zeros(m)
            e[self.reads.index(sensor)] = 1.0
            return -self.phi @ self.K @ e, e
        if sensor == "current" and self.phi.shape[0] == 5:    # the force it takes as input
            kf = self.force_per_amp
            return kf * (-self.gamma + self.phi @ self.K @ self.D), -kf * self.D
        return np.zeros(n), np.zeros(m)


def _cov_response(a_e: np.ndarray, H: np.ndarray, b: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The innovation covariance of e+ = a_e e + b w, nu = H e + d w for unit white w."""
    P = exact.solve_stein(a_e, np.outer(b, b))
    return exact.product(H, P, H.T) + np.outer(d, d)


def check_options(opts: DesignOptions) -> None:
    """The bank's design options, each one clear error."""
    if opts.fdi_bank_structure not in ("voltage", "force"):
        raise ValueError(f"fdi_bank_structure must be 'voltage' or 'force', "
                         f"got {opts.fdi_bank_structure!r}")
    if not (opts.fdi_bank_offset_walk_v > 0 and math.isfinite(opts.fdi_bank_offset_walk_v)):
        raise ValueError(f"fdi_bank_offset_walk_v must be positive, got "
                         f"{opts.fdi_bank_offset_walk_v}")
    if not 1 <= opts.fdi_bank_window <= 100_000:
        raise ValueError(f"fdi_bank_window must be 1-100000 ticks, got {opts.fdi_bank_window}")


def generators(cfg: VehicleConfig, opts: DesignOptions,
               bridge_open: bool = False) -> dict[str, Generator]:
    """The bank for this vehicle: {blind sensor (or "full"): Generator}. ``bridge_open``:
    the winding model's filters as they run with the bridge open (``_open``)."""
    check_options(opts)
    A5, B5, phi5, gamma5, q_unit5 = filter_discrete(cfg, opts.dt_s)
    design_q = road_intensity_per_mps(GRADE_GQ_M3[opts.akf_q_grade]) * NOMINAL_SPEED_MPS
    kf = cfg.actuator.force_constant_n_per_a
    sig2 = {s: getattr(cfg.sensors, CHANNEL[s]).variance for s in SENSORS}
    cur_var = sig2["current"]
    rows5 = {"ba": (A5[0], B5[0]), "defl": (np.array([0, 0, 1.0, -1.0, 0]), 0.0),
             "wa": (A5[1], B5[1])}
    # the winding model, one for every filter on it
    phi7, gamma7, gamma_f7, H7, q_unit7, q_fixed7 = _winding_model(cfg, opts, A5, B5)
    row = {"ba": H7[0], "defl": H7[1], "wa": H7[2], "current": np.eye(7)[5]}
    out = {}
    voltage = opts.fdi_bank_structure == "voltage"
    for blind, reads in (READS_VOLTAGE if voltage else READS).items():
        if blind == "current" or (voltage and blind != "full"):
            phi, gamma, gamma_f, q_unit, q_fixed = phi7, gamma7, gamma_f7, q_unit7, q_fixed7
            H = np.array([row[c] for c in reads])
            D = np.zeros(len(reads))
            D_f = np.array([B5[0] if c == "ba" else B5[1] if c == "wa" else 0.0 for c in reads])
            r0 = np.diag([sig2[c] for c in reads])
        else:
            phi, gamma = phi5, gamma5
            gamma_f = gamma
            H = np.array([rows5[c][0] for c in reads])
            D = np.array([rows5[c][1] for c in reads])
            D_f = D
            q_unit = q_unit5
            q_fixed = np.zeros((5, 5))
            # the force from the measured current: its noise enters the measurements through D
            r0 = np.diag([sig2[c] for c in reads]) + np.outer(D, D) * kf ** 2 * cur_var
        Q = design_q * q_unit + q_fixed
        K = grid.snap(exact.dare_filter(phi, H, Q, r0)[1])
        a_e = exact.closed_loop(phi, K, H)
        S_road = _cov_lyap(a_e, H, q_unit)
        S_noise = _cov_lyap(a_e, H, _plus(q_fixed, exact.matmul(phi, K, r0, K.T, phi.T))) + r0
        S_force = _cov_response(a_e, H, _plus(gamma_f, -exact.matmul(phi, K, D_f)), D_f)
        g = Generator(blind=blind, reads=reads, phi=phi, gamma=gamma, gamma_force=gamma_f,
                      H=H, D=D, D_force=D_f, K=K, r0=r0, q_unit=q_unit, q_fixed=q_fixed,
                      S_road=S_road, S_noise=S_noise, S_force=S_force, force_per_amp=kf)
        out[blind] = _open(g, phi5, gamma5, q_unit5, design_q) if (
            bridge_open and g.phi.shape[0] == 7) else g
    return out


def _open(g: Generator, phi5, gamma5, q_unit5, design_q: float) -> Generator:
    """A winding-model filter with the bridge open: no current flows, so neither the
    current nor the voltage offset (which drives nothing then) is a state; the car's five
    states are predicted without the actuator and corrected with the steady-state gain of
    that model. The current it reads is its sensor's noise alone (its gain column zero), so
    a current sensor reading a current then is plainly wrong. Designed apart from the
    driven filter: that one's gain counts on the winding's back-EMF as a measurement of the
    relative velocity, and with it the filter blind to WA sat above its level (1.1-1.2
    against 1.163) in fault-free passive driving."""
    H = g.H[:, :5]
    K = grid.snap(exact.dare_filter(phi5, H, design_q * q_unit5, g.r0)[1])
    a_e = exact.closed_loop(phi5, K, H)
    zero = np.zeros((5, 5))
    return Generator(
        blind=g.blind, reads=g.reads, phi=phi5, gamma=np.zeros(5), gamma_force=gamma5,
        H=H, D=np.zeros(len(g.reads)), D_force=g.D_force, K=K, r0=g.r0, q_unit=q_unit5,
        q_fixed=zero, S_road=_cov_lyap(a_e, H, q_unit5),
        S_noise=_cov_lyap(a_e, H, exact.product(phi5, K, g.r0, K.T, phi5.T)) + g.r0,
        S_force=_cov_response(a_e, H, _plus(gamma5, -exact.matmul(phi5, K, g.D_force)),
                              g.D_force),
        force_per_amp=g.force_per_amp)


def winding_continuous(cfg: VehicleConfig, A5: np.ndarray, B5: np.ndarray) -> np.ndarray:
    """The winding model's continuous A (``_winding_model``)."""
    ap, kf = cfg.actuator, cfg.actuator.force_constant_n_per_a
    L, R = ap.winding_inductance_h, ap.winding_resistance_ohm
    A = np.zeros((7, 7))
    A[:5, :5] = A5
    A[:5, 5] = B5 * kf
    A[5, 5] = -R / L
    A[5, 0], A[5, 1] = -kf / L, kf / L        # the back-EMF (K_e = K_f, the ideal screw)
    A[5, 6] = 1.0 / L
    return A


def _winding_model(cfg: VehicleConfig, opts: DesignOptions, A5: np.ndarray, B5: np.ndarray):
    """The winding model: x = [zs_dot, zt_dot, zs, zt, zf, i, v_off], the
    winding L di/dt = V + v_off - R i - K_e (zs_dot - zt_dot) driven by the voltage the bridge
    applies, the force K_f i, and v_off a random walk that takes up what the voltage model
    misses (the supply's measurement, the winding's resistance, the back-EMF constant). Returns
    (phi, gamma_voltage, gamma_force, H, q_unit, q_fixed)."""
    dt = opts.dt_s
    A = winding_continuous(cfg, A5, B5)
    n = A.shape[0]
    B = np.zeros(n)
    B[5] = 1.0 / cfg.actuator.winding_inductance_h
    phi = exact.expm(A * dt)
    gamma = zoh_input(A, B, dt)
    gamma_f = zoh_input(A, np.append(B5, [0.0, 0.0]), dt)
    H = np.array([A[0], [0, 0, 1.0, -1.0, 0, 0, 0], A[1]])
    e = np.zeros(n)
    e[4] = 1.0
    q_unit = van_loan_integral(A.T, np.outer(e, e), dt)
    # the voltage the ECU knows: the supply's sample noise (taken as white, though a sample
    # holds for 10 ms); the offset's walk
    v_var = cfg.sensors.supply_voltage.variance
    e[:] = 0.0
    e[6] = 1.0
    q_fixed = np.outer(gamma, gamma) * v_var + van_loan_integral(
        A.T, np.outer(e, e), dt) * opts.fdi_bank_offset_walk_v ** 2
    return phi, gamma, gamma_f, H, q_unit, q_fixed


def _open_phi(cfg: VehicleConfig, opts: DesignOptions) -> np.ndarray:
    """The winding model's transition with the bridge open: no current flows (the winding's
    row is zero, so the current state stays at the zero the filter sets) and the car moves
    without the actuator's force."""
    A = winding_continuous(cfg, *filter_continuous(cfg))
    A[5, :] = 0.0
    return exact.expm(A * opts.dt_s)


def _cov_lyap(a_e: np.ndarray, H: np.ndarray, Q: np.ndarray) -> np.ndarray:
    P = exact.solve_stein(a_e, Q)
    return exact.product(H, P, H.T)


def _plus(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a + b (b in extended precision), float64."""
    return np.asarray(exact.ld(a) + b, dtype=float)


def road_intensity(cfg: VehicleConfig, opts: DesignOptions, grade: str, speed: float) -> float:
    """The white-noise intensity driving the road state for ``grade`` at ``speed``."""
    return road_intensity_per_mps(GRADE_GQ_M3[grade]) * speed


def sensor_sigma(cfg: VehicleConfig, sensor: str) -> float:
    """One sample's noise std of a sensor, its quantisation included."""
    return math.sqrt(getattr(cfg.sensors, CHANNEL[sensor]).variance)


def bank_params(cfg: VehicleConfig, opts: DesignOptions):
    """The firmware's bank (``firmware.params.BankParams``): the voltage structure's four
    filters, filter k blind to ``SENSORS[k]``."""
    from calib.fdi_design import chi2_level
    from firmware import params as fp

    if opts.fdi_bank_structure != "voltage":
        raise ValueError("the firmware's bank runs the voltage structure only")
    bank, bank_open = generators(cfg, opts), generators(cfg, opts, bridge_open=True)
    gens = [bank[k] for k in SENSORS]
    opens = [bank_open[k] for k in SENSORS]
    chan = {"ba": 0, "defl": 1, "wa": 2, "current": 3}
    w = opts.fdi_bank_window
    stack = lambda f: np.ascontiguousarray(np.array([f(g) for g in gens], dtype=float))  # noqa: E731
    phi_open = _open_phi(cfg, opts)
    return fp.BankParams(
        phi=stack(lambda g: g.phi), phi_open=stack(lambda g: phi_open),
        gamma=stack(lambda g: g.gamma),
        gamma_force=stack(lambda g: g.gamma_force), D_force=stack(lambda g: g.D_force),
        H=stack(lambda g: g.H),
        K=stack(lambda g: g.K), reads=tuple(chan[c] for g in gens for c in g.reads),
        S_road=stack(lambda g: g.S_road), S_noise=stack(lambda g: g.S_noise),
        S_force=stack(lambda g: g.S_force),
        # (the open-bridge gains padded to the seven states: rows 5, 6 zero)
        K_open=np.ascontiguousarray(np.array([np.pad(g.K, ((0, 2), (0, 0)))
                                              for g in opens])),
        S_road_open=np.ascontiguousarray(np.array([g.S_road for g in opens])),
        S_noise_open=np.ascontiguousarray(np.array([g.S_noise for g in opens])),
        lam=2.0 / (w + 1),
        level=chi2_level(3 * w, opts.fdi_false_alarm),
        confirm_ticks=int(round(opts.fdi_bank_confirm_s / opts.dt_s)),
        act_ticks=int(round(opts.fdi_bank_actuator_s / opts.dt_s)),
        decide_ticks=int(round(opts.fdi_bank_decide_s / opts.dt_s)))
