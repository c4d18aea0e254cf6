"""Build the ECU calibration (``firmware.params.EcuParams``) from a vehicle file, the design
tools and the GA-LQR gains file. This is the offline side: it may use scipy; the firmware only
receives numbers.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.linalg import expm

from firmware import params as fp
from hil.config import PACKAGE_DIR, ConfigError, VehicleConfig, default_vehicle
from hil.model import linear_model, mechanics, state_covariance, van_loan_integral
from hil.road import (CONVENTIONS, DEFAULT_CUTOFF_N_PER_M, GRADE_GQ_M3, N0_PER_M)

GAINS_DIR = PACKAGE_DIR / "gains"
NOMINAL_SPEED_MPS = 20.0


@dataclass(frozen=True)
class DesignOptions:
    """Design choices of the calibration (documented defaults)."""

    dt_s: float = 0.001
    use_wheel_accel: bool = True          # AKF measurement vector [BA, SWS, WA] vs [BA, SWS]
    akf_adaptive: bool = True
    akf_bias_adaptive: bool = False
    akf_forgetting: float = 0.9995
    akf_q_grade: str = "C"                # road intensity the AKF assumes before a grade estimate
    akf_q_follows_grade: bool = True      # then the estimated G_q, at most the nominal
    classifier: int = 0                   # 0 road estimate (default), 1 paper's Table 2
    safety_bound: float = 0.955           # LQR safety design: BA, SWS <= bound * passive
    comprehensive_bound: tuple = (0.95, 0.95, 0.95)  # GA-LQR constraint (44) with margins,
    # per output [BA, SWS, DTD]: the ECU's estimation and force tracking cost a few per cent
    skyhook_c: float = 3000.0
    pid_ki: float = 3500.0
    bp_scale: tuple = (10.0, 3000.0, 0.02)   # K_d: the loop K_d / (m_s dt) must stay well below 1
    bp_eta: float = 0.02
    bp_alpha: float = 0.05
    bp_seed: int = 7
    regen_c: float = 550.0
    regen_skyhook_c: float = 1200.0
    regen_min_voltage_ratio: float = 0.5
    ramp_s: float = 0.3
    initial_mode: int = fp.MODE_PASSIVE


def _zoh_input(A: np.ndarray, B: np.ndarray, dt: float) -> np.ndarray:
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A
    M[:n, n] = B
    return expm(M * dt)[:n, n]


def akf_model(cfg: VehicleConfig, opts: DesignOptions, convention: str = "iso") -> fp.AkfParams:
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
    A[4, 4] = -2.0 * math.pi * DEFAULT_CUTOFF_N_PER_M * NOMINAL_SPEED_MPS
    B = np.append(b_force, 0.0)
    dt = opts.dt_s
    phi = expm(A * dt)
    gamma = np.ascontiguousarray(_zoh_input(A, B, dt))   # (a column slice otherwise)
    e5 = np.eye(5)[4]
    q_unit = van_loan_integral(A.T, np.outer(e5, e5), dt)
    road_int = (2 * math.pi * N0_PER_M) ** 2 * CONVENTIONS[convention] * GRADE_GQ_M3[opts.akf_q_grade]
    rows_H = [A[0], np.array([0, 0, 1.0, -1.0, 0]), A[1]]
    rows_D = [1.0 / vp.sprung_mass_kg, 0.0, -1.0 / vp.unsprung_mass_kg]
    chans = [cfg.sensors.body_accel, cfg.sensors.susp_defl, cfg.sensors.wheel_accel]
    m = 3 if opts.use_wheel_accel else 2
    H = np.array(rows_H[:m])
    D = np.array(rows_D[:m])
    quant = np.array([c.lsb ** 2 / 12.0 for c in chans[:m]])
    r0 = np.diag(np.array([c.noise_std ** 2 for c in chans[:m]]) + quant)
    # the known force comes from the measured current: its noise enters BA and WA together
    cur = cfg.sensors.motor_current
    force_var = (ap.force_constant_n_per_a) ** 2 * (cur.noise_std ** 2 + cur.lsb ** 2 / 12.0)
    r0 = r0 + np.outer(D, D) * force_var
    # initial covariance: the stationary one of the passive car on the nominal road
    model = linear_model(vp, GRADE_GQ_M3[opts.akf_q_grade], NOMINAL_SPEED_MPS, convention)
    p0 = state_covariance(model.A, model.G)
    return fp.AkfParams(phi=phi, gamma=gamma, q_unit=q_unit, road_intensity_per_mps=road_int,
                        H=H, D=D, r0=r0, r_floor=quant, forgetting=opts.akf_forgetting,
                        adaptive=opts.akf_adaptive, bias_adaptive=opts.akf_bias_adaptive, p0=p0)


GRADE_HP_HZ = 0.5
GRADE_LP_HZ = 20.0


def grade_band_variance(speed: float, dt: float, hp_a: float, lp_a: float,
                        convention: str = "iso") -> float:
    """Variance of the band-passed road velocity for a unit-G_q road at ``speed``: the exact
    AR(1) road at the tick, differenced, high-passed, low-passed (frequency-domain integral)."""
    lam = 2 * math.pi * DEFAULT_CUTOFF_N_PER_M * speed
    a2 = (2 * math.pi * N0_PER_M) ** 2 * CONVENTIONS[convention] * speed
    phi = math.exp(-lam * dt)
    q = a2 * (1 - phi * phi) / (2 * lam)
    w = np.concatenate([[0.0], np.geomspace(1e-8, math.pi, 6000)])  # resolves the road pole
    z1 = np.exp(-1j * w)
    s_road = q / np.abs(1 - phi * z1) ** 2
    H = ((1 - z1) / dt) * (hp_a * (1 - z1) / (1 - hp_a * z1)) * (lp_a / (1 - (1 - lp_a) * z1))
    return float(np.trapezoid(s_road * np.abs(H) ** 2, w) / math.pi)


def grade_params(cfg: VehicleConfig, opts: DesignOptions) -> fp.GradeParams:
    from tools.analysis import thresholds

    dt = opts.dt_s
    rc_h = 1 / (2 * math.pi * GRADE_HP_HZ)
    rc_l = 1 / (2 * math.pi * GRADE_LP_HZ)
    hp_a, lp_a = rc_h / (rc_h + dt), dt / (rc_l + dt)
    speeds = np.arange(1.0, 61.0, 1.0)
    var = np.array([grade_band_variance(v, dt, hp_a, lp_a) for v in speeds])
    th = thresholds(cfg, "iso")
    return fp.GradeParams(
        classifier=opts.classifier, hp_a=hp_a, lp_a=lp_a, block_ticks=int(round(0.25 / dt)),
        n_blocks=6, speed_grid=speeds, var_per_gq=var,
        gq_centres=np.array([GRADE_GQ_M3[g] for g in "ABCD"]), hysteresis=0.15,
        dwell_ticks=int(round(0.5 / dt)), min_speed=2.0,
        dtd1=th["dtd1_m"], ba1=th["ba1_mps2"], ba2=th["ba2_mps2"])


def vehicle_digest(cfg: VehicleConfig) -> str:
    v = cfg.vehicle
    text = json.dumps([v.sprung_mass_kg, v.unsprung_mass_kg, v.spring_stiffness_n_per_m,
                       v.damping_n_s_per_m, v.tire_stiffness_n_per_m])
    return hashlib.sha256(text.encode()).hexdigest()


def default_gains_path(cfg: VehicleConfig) -> Path:
    return GAINS_DIR / f"galqr_{vehicle_digest(cfg)[:12]}.json"


def load_gains(path: Path, cfg: VehicleConfig) -> np.ndarray:
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read gains file: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: invalid JSON: {exc}") from None
    K = data.get("K") if isinstance(data, dict) else None
    if (not isinstance(K, list) or len(K) != 5
            or not all(isinstance(k, (int, float)) and math.isfinite(k) for k in K)):
        raise ConfigError(f"{path}: key 'K' must be a list of 5 finite numbers")
    if data.get("vehicle_sha256") not in (None, vehicle_digest(cfg)):
        raise ConfigError(f"{path}: gains were tuned for another vehicle "
                          f"(vehicle_sha256 differs); re-run python -m tools.tune_ga_lqr")
    return np.array(K, dtype=float)


def comprehensive_gain(cfg: VehicleConfig, opts: DesignOptions, gains_file: Path | None) -> np.ndarray:
    """The GA-LQR gain: from ``gains_file``, else the shipped file for this vehicle, else
    tuned now by the GA with its default seed (deterministic, about a second)."""
    if gains_file is not None:
        return load_gains(gains_file, cfg)
    shipped = default_gains_path(cfg)
    if shipped.exists():
        return load_gains(shipped, cfg)
    from tools.tune_ga_lqr import tune

    result = tune(cfg, 0, opts.comprehensive_bound)
    if not result["feasible"]:
        raise ConfigError(f"{cfg.source}: GA-LQR found no gains meeting Eq. (44) with margin")
    return np.array(result["K"])


def build(cfg: VehicleConfig | None = None, opts: DesignOptions | None = None,
          gains_file: Path | None = None) -> fp.EcuParams:
    from tools.linear import safety_design

    cfg = cfg or default_vehicle()
    opts = opts or DesignOptions()
    vp, ap, sp = cfg.vehicle, cfg.actuator, cfg.sensors
    dt = opts.dt_s

    def chan(c):
        return fp.AdcChannel(range_min=c.range_min, lsb=c.lsb, full_scale=2 ** c.bits - 1)

    adc = fp.AdcParams(chan(sp.body_accel), chan(sp.wheel_accel), chan(sp.susp_defl),
                       chan(sp.motor_current), chan(sp.speed), rail_ticks=3, recover_ticks=50)
    plant = fp.PlantParams(vp.sprung_mass_kg, vp.unsprung_mass_kg, vp.spring_stiffness_n_per_m,
                           vp.damping_n_s_per_m, vp.tire_stiffness_n_per_m,
                           ap.viscous_friction_n_s_per_m, ap.force_constant_n_per_a,
                           ap.screw_efficiency, ap.winding_resistance_ohm,
                           ap.winding_inductance_h, ap.current_limit_a, ap.bus_voltage_v,
                           ap.storage_voltage_v)
    model = linear_model(vp, GRADE_GQ_M3["C"], NOMINAL_SPEED_MPS)
    k_safety = safety_design(model, opts.safety_bound).K
    k_comp = comprehensive_gain(cfg, opts, gains_file)
    rng = np.random.default_rng(opts.bp_seed)
    force_limit = 0.95 * ap.current_limit_a * ap.force_constant_n_per_a * ap.screw_efficiency
    control = fp.ControlParams(
        k_safety=k_safety, k_comprehensive=k_comp, skyhook_c=opts.skyhook_c,
        skyhook_passive_c=0.0, pid_kp=0.0, pid_ki=opts.pid_ki, pid_kd=0.0,
        pid_leak=1.0 - dt / 1.5,
        bp_w_hidden=rng.normal(0.0, 0.5, (5, 4)), bp_b_hidden=rng.normal(0.0, 0.5, 5),
        bp_w_out=rng.normal(0.0, 0.5, (3, 5)), bp_b_out=np.zeros(3),
        bp_eta=opts.bp_eta, bp_alpha=opts.bp_alpha, bp_scale=np.array(opts.bp_scale, dtype=float),
        bp_input_scale=1.0, regen_c=opts.regen_c, regen_skyhook_c=opts.regen_skyhook_c,
        regen_min_voltage_ratio=opts.regen_min_voltage_ratio, force_limit=force_limit)
    a = math.exp(-ap.winding_resistance_ohm * dt / ap.winding_inductance_h)
    bc = (1 - a) / ap.winding_resistance_ohm
    actuator = fp.ActuatorParams(current_a=a, current_b=bc, ki=0.2 / bc,
                                 integ_limit=0.2 * ap.bus_voltage_v)
    controllers = (fp.CTRL_NONE, fp.CTRL_REGEN, fp.CTRL_BPPID, fp.CTRL_LQR, fp.CTRL_GALQR)
    static_defl = vp.static_tire_load_n / vp.tire_stiffness_n_per_m
    modes = fp.ModeParams(ramp_ticks=int(round(opts.ramp_s / dt)),
                          safety_dtd_rms_limit=0.55 * static_defl, safety_exit_ratio=0.8,
                          safety_window_ticks=int(round(1.0 / dt)),
                          safety_hold_ticks=int(round(2.0 / dt)),
                          initial_mode=opts.initial_mode, controllers=controllers)
    return fp.EcuParams(dt_s=dt, adc=adc, plant=plant, akf=akf_model(cfg, opts),
                        grade=grade_params(cfg, opts), modes=modes, control=control,
                        actuator=actuator, akf_q_follows_grade=opts.akf_q_follows_grade,
                        akf_q_gq_nominal=GRADE_GQ_M3[opts.akf_q_grade])


def with_controllers(params: fp.EcuParams, mode: int, controller: int) -> fp.EcuParams:
    """Override the controller of one mode (``hil sim --controller``)."""
    ctrls = list(params.modes.controllers)
    ctrls[mode] = controller
    return replace(params, modes=replace(params.modes, controllers=tuple(ctrls)))
