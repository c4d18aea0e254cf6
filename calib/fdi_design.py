"""The model-based fault detection's parameters (``firmware.diag.fdi``): the innovation and
actuator tests' EWMA levels at the designed false-alarm rate, the flatline tests' run lengths,
the supply's operating range (docs/diagnostics.md)."""

from __future__ import annotations

import math

from calib.options import DesignOptions
from calib.vehicle import VehicleConfig
from firmware import params as fp

def _ewma_level(window: int, alpha: float) -> tuple[float, float]:
    """EWMA weight 2/(W+1) and its alarm level chi2_nu(1-alpha)/nu, nu = (2-lam)/lam = W:
    the EWMA of chi2(1) samples has mean 1 and variance lam/(2-lam), that of chi2_nu/nu.
    (chi2_nu's quantile as scipy.stats.chi2.ppf computes it, without importing scipy.stats,
    which took about a second of every run's start.)"""
    lam = 2.0 / (window + 1)
    return lam, chi2_level((2.0 - lam) / lam, alpha)


def chi2_level(dof: float, alpha: float) -> float:
    """chi2_dof(1 - alpha) / dof: the level of an EWMA test whose statistic is about
    chi2_dof / dof (dof = W for one channel, m W for m whitened channels)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(dof / 2.0, 1.0 - alpha) / dof)


def flatline_ticks(noise_std: float, lsb: float, alpha: float, max_p: float) -> int:
    """Identical counts in a row with probability below ``alpha`` for a healthy channel:
    two samples with independent noise of std sigma fall on the same count with probability
    at most q / (2 sigma sqrt(pi)) (the density of their difference at 0 times one step);
    0 (no test) where that is ``max_p`` or more."""
    if noise_std <= 0:
        return 0
    p = lsb / (2.0 * noise_std * math.sqrt(math.pi))
    if p >= max_p:
        return 0
    return 1 + math.ceil(math.log(alpha) / math.log(p))


def fdi_params(cfg: VehicleConfig, opts: DesignOptions) -> fp.FdiParams:
    from firmware.safety import RX_CHECKS

    ap, sp, nl = cfg.actuator, cfg.sensors, cfg.nonlinear
    dt = opts.dt_s
    o = opts
    lam, level = _ewma_level(o.fdi_nis_window, o.fdi_false_alarm)
    act_lam, act_level = _ewma_level(o.fdi_act_window, o.fdi_false_alarm)
    cur, sup = sp.motor_current, sp.supply_voltage
    eta = ap.screw_efficiency
    a = math.exp(-ap.winding_resistance_ohm * dt / ap.winding_inductance_h)
    cur_sigma = math.sqrt(cur.variance)
    supply_period = next(c for c in RX_CHECKS if c.message == "PLANT_SUPPLY").ticks(dt)[0]
    return fp.FdiParams(
        nis_lambda=lam, nis_threshold=level,
        flat_ticks=tuple(flatline_ticks(c.noise_std, c.lsb, o.fdi_false_alarm, o.flatline_max_p)
                         for c in (
            sp.body_accel, sp.wheel_accel, sp.susp_defl, sp.motor_current)),
        force_band=1.0 / eta - eta,
        valid_defl_m=nl.bump_stop_clearance_m - 5.0 * sp.susp_defl.noise_std,
        hold_ticks=o.fdi_hold_windows * o.fdi_nis_window,
        cur_sigma_a=cur_sigma,
        # the residual i_k - a i_{k-1} - b (V - EMF), the EMF from the step before:
        # n_k - (1 + a) n_{k-1} + a n_{k-2} in the current noise n
        act_var=cur_sigma ** 2 * (1.0 + (1.0 + a) ** 2 + a * a),
        act_lambda=act_lam, act_threshold=act_level,
        act_confirm_ticks=supply_period + 1,
        act_retry_ticks=int(round(o.fdi_act_retry_s / dt)),
        act_flat_ticks=tuple(flatline_ticks(c.noise_std, c.lsb, o.fdi_act_suspect,
                                            o.flatline_max_p) or 1 << 30
                             for c in (sp.body_accel, sp.wheel_accel)),
        open_ratio=o.fdi_open_sigmas,
        supply_offset_v=sup.range_min, supply_lsb_v=sup.lsb, supply_full_scale=2 ** sup.bits - 1,
        supply_change_v=5.0 * math.sqrt(2.0) * math.hypot(sup.noise_std, sup.lsb / math.sqrt(12))
        + sup.lsb,
        supply_low_v=o.supply_low_ratio * ap.bus_voltage_v,
        supply_high_v=o.supply_high_ratio * ap.bus_voltage_v,
        settle_ticks=int(round(o.fdi_settle_s / dt)),
        clip_sq=o.fdi_clip_sigmas ** 2, actuator_verdicts=o.fdi_actuator_verdicts,
        nis_verdicts=o.fdi_nis_verdicts)
