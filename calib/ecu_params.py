"""Build the ECU calibration (``firmware.params.EcuParams``) from a vehicle, the design options
(``calib.options``) and the GA-LQR gains file. This is the offline side: it may use scipy; the
firmware only receives numbers.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import replace
from pathlib import Path
import numpy as np

from calib import cache, calpage, dataset, exact, grid
from calib.control_design import (_feedback_designs, comprehensive_gain, damping_scale,
                                   default_gains_path)
from calib.errors import ConfigError
from calib import fdi_bank
from calib.fdi_design import fdi_params
from calib.iso8608 import DEFAULT_CUTOFF_N_PER_M, GRADE_GQ_M3, road_intensity_per_mps
from calib.model import (filter_continuous, filter_discrete, linear_model, paper_thresholds,
                         zoh_input)
from calib.options import NOMINAL_SPEED_MPS, DesignOptions
from calib.vehicle import VehicleConfig
from firmware import params as fp


def akf_model(cfg: VehicleConfig, opts: DesignOptions, convention: str = "iso") -> fp.AkfParams:
    vp, ap = cfg.vehicle, cfg.actuator
    dt = opts.dt_s
    A, B, phi, gamma, q_unit = filter_discrete(cfg, dt)
    road_int = road_intensity_per_mps(GRADE_GQ_M3[opts.akf_q_grade], convention)
    rows_H, rows_D = model_outputs(cfg, A)
    chans = [cfg.sensors.body_accel, cfg.sensors.susp_defl, cfg.sensors.wheel_accel]
    m = 3 if opts.use_wheel_accel else 2
    H = np.array(rows_H[:m])
    D = np.array(rows_D[:m])
    quant = np.array([c.lsb ** 2 / 12.0 for c in chans[:m]])
    r0 = np.diag(np.array([c.noise_std ** 2 for c in chans[:m]]) + quant)
    # the known force comes from the measured current: its noise enters BA and WA together
    cur = cfg.sensors.motor_current
    force_var = (ap.force_constant_n_per_a) ** 2 * cur.variance
    r0 = r0 + np.outer(D, D) * force_var
    # initial covariance: the stationary one of the passive car on the nominal road
    model = linear_model(vp, GRADE_GQ_M3[opts.akf_q_grade], NOMINAL_SPEED_MPS, convention)
    p0 = grid.snap(exact.solve_lyap(model.A, np.outer(model.G, model.G)))
    # off the linear model (firmware.akf): the bump stops as a known force where the vehicle
    # has them; an airborne tyre (where it can lift off) and a current beyond its sensor's
    # range as unknown forces of the size of the static load and of that current's force
    nl, ba_ch, wa_ch = cfg.nonlinear, cfg.sensors.body_accel, cfg.sensors.wheel_accel
    gamma_wheel = zoh_input(A, np.array([0, 1 / vp.unsprung_mass_kg, 0, 0, 0.0]), dt)
    tyre_sigma = math.hypot(vp.sprung_mass_kg * math.hypot(ba_ch.noise_std, ba_ch.lsb / math.sqrt(12)),
                            vp.unsprung_mass_kg * math.hypot(wa_ch.noise_std, wa_ch.lsb / math.sqrt(12)))
    cur_range = max(abs(cur.range_min), abs(cur.range_max))
    sws = cfg.sensors.susp_defl
    return fp.AkfParams(phi=phi, gamma=gamma, q_unit=q_unit, road_intensity_per_mps=road_int,
                        H=H, D=D, r0=r0, r_floor=quant, forgetting=opts.akf_forgetting,
                        adaptive=opts.akf_adaptive, bias_adaptive=opts.akf_bias_adaptive, p0=p0,
                        bump_clearance_m=nl.bump_stop_clearance_m if nl.bump_stops else 0.0,
                        bump_stiffness=nl.bump_stop_stiffness_n_per_m if nl.bump_stops else 0.0,
                        gamma_wheel=gamma_wheel, tyre_load_n=vp.static_tire_load_n,
                        tyre_force_sigma_n=tyre_sigma, lift_sigmas=opts.akf_lift_sigmas,
                        lift_force_sigma_n=vp.static_tire_load_n if nl.tire_lift_off else 0.0,
                        current_force_sigma_n=(ap.force_constant_n_per_a * cur_range
                                               / ap.screw_efficiency),
                        stroke_force_sigma_n=(nl.bump_stop_stiffness_n_per_m * max(
                            0.0, max(-sws.range_min, sws.range_max) - nl.bump_stop_clearance_m)
                            if nl.bump_stops else 0.0))


def grade_band_variance(speed: float, dt: float, hp_a: float, lp_a: float,
                        convention: str = "iso") -> float:
    """Variance of the band-passed road velocity for a unit-G_q road at ``speed``: the exact
    AR(1) road at the tick, differenced, high-passed, low-passed (frequency-domain integral)."""
    lam = 2 * math.pi * DEFAULT_CUTOFF_N_PER_M * speed
    a2 = road_intensity_per_mps(1.0, convention) * speed
    phi = math.exp(-lam * dt)
    q = a2 * (1 - phi * phi) / (2 * lam)
    w = np.concatenate([[0.0], np.geomspace(1e-8, math.pi, 6000)])  # resolves the road pole
    z1 = np.exp(-1j * w)
    s_road = q / np.abs(1 - phi * z1) ** 2
    H = ((1 - z1) / dt) * (hp_a * (1 - z1) / (1 - hp_a * z1)) * (lp_a / (1 - (1 - lp_a) * z1))
    return float(np.trapezoid(s_road * np.abs(H) ** 2, w) / math.pi)


def grade_params(cfg: VehicleConfig, opts: DesignOptions) -> fp.GradeParams:
    dt = opts.dt_s
    rc_h = 1 / (2 * math.pi * opts.grade_hp_hz)
    rc_l = 1 / (2 * math.pi * opts.grade_lp_hz)
    hp_a, lp_a = rc_h / (rc_h + dt), dt / (rc_l + dt)
    speeds = np.arange(1.0, 61.0, 1.0)
    # (on the grid: numpy's exp and log are vectorised differently with and without AVX-512)
    var = grid.snap(np.array([grade_band_variance(v, dt, hp_a, lp_a) for v in speeds]))
    dtd1, ba1, ba2 = (grid.snap(v) for v in paper_thresholds(cfg.vehicle, "iso"))
    return fp.GradeParams(
        classifier=opts.classifier, hp_a=hp_a, lp_a=lp_a,
        block_ticks=int(round(opts.grade_block_s / dt)), n_blocks=opts.grade_blocks,
        speed_grid=speeds, var_per_gq=var,
        gq_centres=np.array([GRADE_GQ_M3[g] for g in "ABCD"]), hysteresis=opts.grade_hysteresis,
        dwell_ticks=int(round(opts.grade_dwell_s / dt)), min_speed=opts.grade_min_speed_mps,
        dtd1=dtd1, ba1=ba1, ba2=ba2)


# Table 3's body: the damping-like gains of calib.options are set for it
def build(cfg: VehicleConfig, opts: DesignOptions | None = None,
          gains_file: Path | None = None) -> fp.EcuParams:
    """The ECU's calibration for ``cfg``; a vehicle it cannot be designed for (no
    stabilising LQR, a non-finite design) is a ConfigError with the reason. Kept in the
    design cache (``calib.cache``) under every input: the vehicle as parsed, the options, the
    gains file's bytes, the design code."""
    opts = opts or DesignOptions()
    if opts.calibration:            # (the design as built, then the values set on it)
        return calpage.apply(build(cfg, replace(opts, calibration=()), gains_file),
                             opts.calibration)
    shipped = dataset.lookup(design_key(cfg, gains_file, opts))
    if shipped is not None:         # (a shipped car: its committed calibration, calib.dataset)
        return shipped
    gains = Path(gains_file or default_gains_path(cfg))
    parts = (repr(cfg).encode(), json.dumps(dataclasses.asdict(opts), sort_keys=True).encode(),
             str(gains_file is not None).encode(),
             gains.read_bytes() if gains.is_file() else b"<no gains file: tuned at build time>")
    try:
        return cache.cached("ecu_params", parts, lambda: _build(cfg, opts, gains_file))
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise ConfigError(f"{cfg.source}: no ECU calibration for this vehicle: {exc}") from None


def degraded_modes(text: str, key: str) -> int:
    """The bits (``firmware.params.MODE_*``) of a space-separated list of mode names."""
    bits = 0
    for name in text.split():
        if name not in fp.MODE_NAMES[1:]:
            raise ValueError(f"{key}: unknown mode {name!r} (one of "
                             f"{', '.join(fp.MODE_NAMES[1:])})")
        bits |= 1 << fp.MODE_NAMES.index(name)
    return bits


def model_outputs(cfg: VehicleConfig, A: np.ndarray) -> tuple[list, list]:
    """The filter model's outputs (``A``: ``filter_continuous``'s, the state [zs', zt', zs, zt,
    zf]) in the filter's measurement order BA, SWS, WA: their rows of H and D (the known
    force's feedthrough)."""
    vp = cfg.vehicle
    return ([A[0], np.array([0, 0, 1.0, -1.0, 0]), A[1]],
            [1.0 / vp.sprung_mass_kg, 0.0, -1.0 / vp.unsprung_mass_kg])


def degrade_params(cfg: VehicleConfig, opts: DesignOptions, A: np.ndarray
                   ) -> fp.DegradeParams:
    """Degraded operation (``firmware.diag.degrade``): the model's output of each sensor for
    the virtual sensor (``model_outputs`` in the ADC's order BA, WA, SWS), and the modes kept
    without each (the motor current: none)."""
    rows_H, rows_D = model_outputs(cfg, A)
    order = (0, 2, 1)
    modes = tuple(degraded_modes(getattr(opts, f"degraded_modes_{name}"),
                                 f"degraded_modes_{name}")
                  for name in ("body_accel", "wheel_accel", "susp_defl")) + (0,)
    return fp.DegradeParams(H=np.array([rows_H[i] for i in order]),
                            D=np.array([rows_D[i] for i in order]), modes=modes,
                            readmit_ticks=int(round(opts.degraded_readmit_s / opts.dt_s)),
                            readmissions=opts.degraded_readmissions)


def current_rail_mps(cfg: VehicleConfig, opts: DesignOptions) -> float:
    """The relative velocity beyond which a motor current at its sensor's rail is explained
    (``firmware.adc``): the margin times the velocity at which the back-EMF K v alone, against
    the lower of the bus and storage voltages, drives the current I_rail = the smaller rail's
    magnitude through the winding R: (V + R I_rail) / K. (The bridge's hardware limit keeps
    the current it drives itself below the rail; only the back-EMF takes it further.)"""
    ap, cur = cfg.actuator, cfg.sensors.motor_current
    i_rail = min(abs(cur.range_min), abs(cur.range_max))
    v = min(ap.bus_voltage_v, ap.storage_voltage_v)
    return opts.adc_current_rail_margin * (v + ap.winding_resistance_ohm * i_rail) \
        / ap.force_constant_n_per_a


def _build(cfg: VehicleConfig, opts: DesignOptions | None, gains_file: Path | None
           ) -> fp.EcuParams:
    opts = opts or DesignOptions()
    vp, ap, sp = cfg.vehicle, cfg.actuator, cfg.sensors
    dt = opts.dt_s

    def chan(c):
        return fp.AdcChannel(range_min=c.range_min, lsb=c.lsb, full_scale=2 ** c.bits - 1)

    adc = fp.AdcParams(chan(sp.body_accel), chan(sp.wheel_accel), chan(sp.susp_defl),
                       chan(sp.motor_current), chan(sp.speed), rail_ticks=opts.adc_rail_ticks,
                       recover_ticks=opts.adc_recover_ticks,
                       current_rail_mps=current_rail_mps(cfg, opts),
                       defl_rail_margin_m=opts.adc_defl_rail_margin_m)
    plant = fp.PlantParams(vp.sprung_mass_kg, vp.unsprung_mass_kg, vp.spring_stiffness_n_per_m,
                           vp.damping_n_s_per_m, vp.tire_stiffness_n_per_m,
                           ap.viscous_friction_n_s_per_m, ap.force_constant_n_per_a,
                           ap.screw_efficiency, ap.winding_resistance_ohm,
                           ap.winding_inductance_h, ap.current_limit_a, ap.bus_voltage_v,
                           ap.storage_voltage_v)
    k_safety, k_comfort, bp_scale = _feedback_designs(cfg, opts)
    k_comp = comprehensive_gain(cfg, opts, gains_file)
    rng = np.random.default_rng(opts.bp_seed)
    scale = damping_scale(vp, opts)
    force_limit = opts.force_limit_margin * ap.current_limit_a * ap.force_constant_n_per_a * ap.screw_efficiency
    control = fp.ControlParams(
        k_safety=k_safety, k_comprehensive=k_comp, k_comfort=k_comfort,
        skyhook_c=opts.skyhook_c * scale,
        skyhook_passive_c=0.0, pid_kp=0.0, pid_ki=opts.pid_ki * scale, pid_kd=0.0,
        pid_leak=1.0 - dt / opts.pid_leak_s,
        bp_w_hidden=rng.normal(0.0, 0.5, (5, 4)), bp_b_hidden=rng.normal(0.0, 0.5, 5),
        bp_w_out=rng.normal(0.0, 0.5, (3, 5)), bp_b_out=np.zeros(3),
        bp_eta=opts.bp_eta, bp_alpha=opts.bp_alpha, bp_scale=bp_scale,
        bp_input_scale=1.0, bp_gain_alpha=min(1.0, dt / opts.bp_gain_tau_s),
        regen_c=opts.regen_c * scale, regen_skyhook_c=opts.regen_skyhook_c * scale,
        regen_min_voltage_ratio=opts.regen_min_voltage_ratio, force_limit=force_limit)
    a = math.exp(-ap.winding_resistance_ohm * dt / ap.winding_inductance_h)
    bc = (1 - a) / ap.winding_resistance_ohm
    actuator = fp.ActuatorParams(current_a=a, current_b=bc, ki=opts.current_ki_ratio / bc,
                                 integ_limit=opts.current_integ_limit_ratio * ap.bus_voltage_v,
                                 current_limit=opts.current_margin * ap.current_limit_a)
    controllers = (fp.CTRL_NONE, fp.CTRL_REGEN, fp.CTRL_BPPID, fp.CTRL_LQR, fp.CTRL_GALQR)
    static_defl = vp.static_tire_load_n / vp.tire_stiffness_n_per_m
    modes = fp.ModeParams(ramp_ticks=int(round(opts.ramp_s / dt)),
                          safety_dtd_rms_limit=opts.safety_dtd_limit * static_defl,
                          safety_exit_ratio=opts.safety_exit_ratio,
                          safety_window_ticks=int(round(opts.safety_window_s / dt)),
                          safety_hold_ticks=int(round(opts.safety_hold_s / dt)),
                          initial_mode=opts.initial_mode, controllers=controllers,
                          request_min_ticks=int(round(opts.request_min_s / dt)))
    return fp.EcuParams(dt_s=dt, adc=adc, plant=plant, akf=akf_model(cfg, opts),
                        grade=grade_params(cfg, opts), modes=modes, control=control,
                        actuator=actuator, akf_q_follows_grade=opts.akf_q_follows_grade,
                        akf_q_gq_nominal=GRADE_GQ_M3[opts.akf_q_grade],
                        fdi=fdi_params(cfg, opts), bank=fdi_bank.bank_params(cfg, opts),
                        degrade=degrade_params(cfg, opts, filter_continuous(cfg)[0]),
                        software_version=SOFTWARE_VERSION,
                        calibration_sha256=bytes.fromhex(inputs_digest(cfg, gains_file, opts)),
                        vehicle_sha256=_vehicle_sha256(cfg))


GENERATOR = "tools/tables.py (python -m tools.tables)"
# part of the calibration hash (DID 0xF1A0, the C tables' header, a campaign row's
# calibration_sha256), which digests the design's inputs, not its numbers: bump it whenever a
# design gives other numbers for the same inputs (2: the comfort law's polish; 3: the same
# numbers on every host: calib.exact, calib.grid, the polish on a lattice)
GENERATOR_VERSION = 3


def design_key(cfg: VehicleConfig, gains_file: Path | None, opts: DesignOptions) -> str:
    """SHA-256 of what a design depends on: the vehicle as parsed (whatever file it came
    from), the design options, the gains file's bytes, the generator's version. The key of a
    committed calibration (``calib.dataset``)."""
    h = hashlib.sha256(f"{GENERATOR} v{GENERATOR_VERSION}\n".encode())
    h.update(repr(replace(cfg, source="")).encode())
    h.update(json.dumps(dataclasses.asdict(opts), sort_keys=True).encode())
    gains = Path(gains_file or default_gains_path(cfg))
    h.update(gains.read_bytes() if gains.is_file() else b"<tuned at build time>")
    return h.hexdigest()


def inputs_digest(cfg: VehicleConfig, gains_file: Path | None, opts: DesignOptions) -> str:
    h = hashlib.sha256()
    h.update(f"{GENERATOR} v{GENERATOR_VERSION}\n".encode())
    h.update(_vehicle_bytes(cfg))
    gains = gains_file or default_gains_path(cfg)
    h.update(Path(gains).read_bytes() if Path(gains).is_file() else b"<tuned at build time>")
    h.update(json.dumps(dataclasses.asdict(opts), sort_keys=True).encode())
    return h.hexdigest()


SOFTWARE_VERSION = "suspension-0.1.0"
def _vehicle_bytes(cfg: VehicleConfig) -> bytes:
    """The vehicle file as read (or the configuration's text when it came from no file)."""
    src = Path(cfg.source)
    return src.read_bytes() if src.is_file() else repr(cfg).encode()


def _vehicle_sha256(cfg: VehicleConfig) -> bytes:
    return hashlib.sha256(_vehicle_bytes(cfg)).digest()


def with_controllers(params: fp.EcuParams, mode: int, controller: int) -> fp.EcuParams:
    """Override the controller of one mode (``hil sim --controller``)."""
    ctrls = list(params.modes.controllers)
    ctrls[mode] = controller
    return replace(params, modes=replace(params.modes, controllers=tuple(ctrls)))
