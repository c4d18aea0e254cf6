"""Every design choice of the calibration in one object, ``DesignOptions``, with documented
defaults; a TOML file can override any of them (``load_options``: a ``[design]`` table whose
keys are the field names; an unknown key, a wrong type or a bad value is one ``ConfigError``
line naming the file and the key)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from calib.errors import ConfigError, read_toml
from firmware.params import MODE_PASSIVE

NOMINAL_SPEED_MPS = 20.0      # speed of the designs' linear models (the paper's v0)


@dataclass(frozen=True)
class DesignOptions:
    """Design choices of the calibration (documented defaults)."""

    dt_s: float = 0.001
    # ADC plausibility (firmware.adc)
    adc_rail_ticks: int = 3               # consecutive samples at a rail that make a fault
    adc_recover_ticks: int = 50           # consecutive good samples that clear it
    # the motor current at its sensor's rail is explained (not a fault) while the estimated
    # relative velocity is at least this share of the one at which the back-EMF alone, against
    # the lower of the bus and storage voltages, drives the current to the rail (the margin
    # covers the estimate's error and the winding's lag, L/R)
    adc_current_rail_margin: float = 0.8
    # the deflection sensor at a rail is explained (not a fault) while the last estimate's
    # stroke, which does not take a clipped stroke as a measurement, is within this of the
    # rail or beyond (a stuck duty drove the stroke there: the sensor was fine)
    adc_defl_rail_margin_m: float = 0.005
    # AKF (firmware.akf)
    use_wheel_accel: bool = True          # AKF measurement vector [BA, SWS, WA] vs [BA, SWS]
    akf_adaptive: bool = True
    akf_bias_adaptive: bool = False
    akf_forgetting: float = 0.9995
    akf_q_grade: str = "C"                # road intensity the AKF assumes before a grade estimate
    akf_q_follows_grade: bool = True      # then the estimated G_q, at most the nominal
    # grade estimate (firmware.grade)
    classifier: int = 0                   # 0 road estimate (default), 1 paper's Table 2
    grade_hp_hz: float = 0.5              # band of the road-velocity estimate
    grade_lp_hz: float = 20.0
    grade_block_s: float = 0.25           # variance blocks ...
    grade_blocks: int = 6                 # ... in the window (1.5 s)
    grade_hysteresis: float = 0.15        # in grade units (log4 G_q)
    grade_dwell_s: float = 0.5            # a new grade must persist this long
    grade_min_speed_mps: float = 2.0      # below this the estimate freezes
    # modes and the road-holding override (firmware.modes)
    ramp_s: float = 0.3                   # crossfade on a controller change
    initial_mode: int = MODE_PASSIVE
    safety_dtd_limit: float = 0.55        # override when the DTD RMS exceeds this x static defl.
    safety_exit_ratio: float = 0.8        # leave it below limit x this ...
    safety_hold_s: float = 2.0            # ... after at least this long in it
    safety_window_s: float = 1.0          # RMS window of the road-holding check
    request_min_s: float = 0.25           # a new driver request sooner than this is spam
    # controllers (firmware.control)
    # LQR safety design: min DTD with SWS <= safety_bound x passive and BA <= the smaller of
    # safety_bound and exp(-z sigma), sigma the scatter of the BA ratio over a drive of
    # ratio_window_s (calib.model.window_scatter): BA stays at most passive on such a drive
    # with z sigma confidence. A lightly damped body scatters most (the default car with its
    # damper x0.7: 2.2 % over 180 s, bound 0.935); a well damped one least (the SUV with its
    # damper x1.3: 0.6 %, so safety_bound)
    safety_bound: float = 0.98
    ratio_window_s: float = 180.0
    ratio_window_z: float = 3.0
    # GA-LQR constraint (44) with margins, per output [BA, SWS, DTD]: each ratio at most this
    # and at most exp(-z sigma) over ratio_window_s at the tuned gain (calib.galqr; the
    # seeds' scatter). The ECU's estimation and force tracking cost little on D (the SUV with
    # its spring x0.7, 180 s, seeds 1-3: the SIL's sum 0.000-0.014 below the design's); a
    # fixed 0.95 for every ratio cost that car 0.080 of the sum
    comprehensive_bound: tuple = (0.98, 0.98, 0.98)
    skyhook_c: float = 3000.0             # (these two as regen_c: Table 3's, scaled per car)
    pid_ki: float = 3500.0
    pid_leak_s: float = 1.5               # time constant of the incremental PID's leak
    # comfort (BP-PID around a state feedback, calib.control_design.comfort_gains): the exact
    # SWS ratio of the law as the ECU runs it (the PID's leak included,
    # calib.control_design.comfort_as_run) and its DTD ratio at most these x passive (the LQR
    # design's own DTD ratio, then the as-run one in calib.control_design.comfort_polish)
    # (SWS also at most exp(-z sigma) over ratio_window_s, as for safety: the seeds' scatter),
    # the suspension's static stiffness at least comfort_min_stiffness x the spring's (half:
    # the whole spring cost the default car 0.016 of BA ratio); the network's gain ranges:
    # K_p up to r0 m_s, K_i up to r1 x the design's body-velocity gain, K_d up to r2 m_s
    # (the loop K_d / (m_s dt) must stay well below 1). DTD keeps a margin to the
    # acceptance's 1.02 (the SIL drives it up to 0.01 above the design)
    comfort_bound: tuple = (0.98, 0.99)
    # ... and exp(-z sigma) less this: the SIL drives the comfort SWS about 2 % above the law
    # as run (the SUV with its sprung mass x1.2, unsprung x1.2, tyre x1.3, spring x0.7, seed 8,
    # B at 20 m/s, 180 s: SIL 1.001-1.004, a linear simulation of the law as run on the same
    # road 0.983-0.985), which took four of 220 cases of the vehicle family past SWS 1.0
    comfort_sws_sil_excess: float = 0.02
    comfort_min_stiffness: float = 0.5
    bp_scale_ratio: tuple = (0.03125, 1.0, 6.25e-5)
    bp_eta: float = 0.02
    # the PID takes the network's gains through a first-order low-pass of this time constant:
    # gains that follow BA within a body cycle rectify it (K_i(BA) x BA has a mean), a static
    # force of some 30 N that lowered the body and raised SWS by up to 20 % (docs/ecu.md)
    bp_gain_tau_s: float = 2.0
    bp_alpha: float = 0.05
    bp_seed: int = 7
    # the energy-feedback law's damping (N s/m) for a body with Table 3's critical damping
    # 2 sqrt(k_s m_s); another car's scales with its own (calib.control_design.damping_scale)
    regen_c: float = 550.0
    regen_skyhook_c: float = 1200.0
    regen_min_voltage_ratio: float = 0.5
    force_limit_margin: float = 0.95      # force limit: this x the current limit's force
    # current loop (firmware.actuator)
    current_ki_ratio: float = 0.2         # integral gain as a fraction of the deadbeat gain
    current_integ_limit_ratio: float = 0.2   # integral clamp as a fraction of the bus voltage
    current_margin: float = 0.95          # the current loop's limit: this x the winding's limit
    # AKF: the wheel is taken as airborne while the measured tyre force is within this many
    # sigma of zero
    akf_lift_sigmas: float = 5.0
    # the fixed damping gains (skyhook_c, pid_ki, regen_c) are set for a body with this car's
    # critical damping 2 sqrt(k_s m_s) (Table 3's); another car's scale with its own
    damping_reference: tuple = (320.0, 20000.0)   # sprung mass kg, spring N/m
    # the safety design's BA bound is a fixed point: at most this many designs, this close
    safety_bound_steps: int = 6
    safety_bound_tol: float = 5e-4
    # comfort: the network's K_i range (N s/m) where the design wants no skyhook; the range
    # the design's SWS bound is searched in; the lattice of the law's polish (each gain a
    # multiple of 2^-bits of its power of two: calib.control_design.lattice_descent)
    comfort_ki_floor: float = 1.0
    comfort_bound_range: tuple = (0.5, 1.2)
    comfort_polish_bits: int = 16
    # model-based fault detection (firmware.diag.fdi, docs/diagnostics.md): the false-alarm
    # probability per test window; the innovation tests' EWMA window (ticks), the actuator
    # test's; a failed actuator test holds the bridge open this long, then retries; BA or WA
    # repeating a count less likely than fdi_act_suspect gives no actuator verdict; the
    # innovation tests wait fdi_hold_windows windows after the model held, and give no
    # verdict before the estimator has run fdi_settle_s; an open winding: |i| within
    # fdi_open_sigmas of zero throughout; one tick's normalised square enters a test at most
    # as fdi_clip_sigmas squared; a channel repeating counts more often than flatline_max_p
    # has no flatline test
    fdi_false_alarm: float = 1e-9
    fdi_nis_window: int = 100
    fdi_act_window: int = 5
    fdi_act_retry_s: float = 0.1
    fdi_act_suspect: float = 0.05
    fdi_hold_windows: int = 3
    fdi_settle_s: float = 1.0
    fdi_open_sigmas: float = 4.0
    fdi_clip_sigmas: float = 5.0
    flatline_max_p: float = 0.9
    fdi_actuator_verdicts: bool = True
    # which innovation tests give verdicts, [BA, SWS, WA]: the WA innovation is dominated by
    # the unmeasured road, whose roughness steps at a segment boundary (B to D: 16x G_q)
    # before the grade estimate follows, so WA's gives none (a WA fault reaches the BA and
    # SWS innovations; a stuck WA its flatline test)
    fdi_nis_verdicts: tuple = (True, True, False)
    # the isolation bank (calib.fdi_bank, firmware.diag.bank; docs/diagnostics.md,
    # "Isolability"): every filter on the winding model ("voltage") or three with the current
    # as their force input ("force"); the random walk of the voltage the winding model
    # misses (V/sqrt(s)); the tests' EWMA window (ticks); after a detection a sensor is named
    # once it alone is left and stayed so fdi_bank_confirm_s, else "not isolated" after
    # fdi_bank_decide_s; a failed actuator test names the actuator unless the bank names BA
    # or WA (its inputs) within fdi_bank_actuator_s
    fdi_bank_structure: str = "voltage"
    fdi_bank_offset_walk_v: float = 0.1
    fdi_bank_window: int = 1000
    fdi_bank_confirm_s: float = 0.1
    fdi_bank_actuator_s: float = 1.0      # the actuator test's conclusion stands after this
    fdi_bank_decide_s: float = 10.0
    # degraded operation (firmware.diag.degrade, docs/degraded.md): the modes kept with each
    # sensor isolated faulty, by name (space-separated; "" none): those that python -m
    # tools.degraded measured as kept without it (the default car, seeds 1-8; the SUV keeps
    # all four). Without the motor current no mode is kept (its loop and the filter's force
    # need it).
    degraded_modes_body_accel: str = "energy comfort safety"
    degraded_modes_wheel_accel: str = "energy comfort"
    degraded_modes_susp_defl: str = "energy comfort safety"
    degraded_readmit_s: float = 2.0       # a sensor out that agrees again this long is used
    degraded_readmissions: int = 1        # again, this often per cycle (then it stays out)
    # the supply's operating range as a fraction of the nominal bus voltage: for 48 V,
    # ISO 21780's range of unlimited operation begins at 36 V and its limited range ends at
    # 54 V. Below, the actuator cannot be relied on for its force; above, the bridge must be
    # protected: either is a safety-relevant fault (the bridge opens)
    supply_low_ratio: float = 0.75
    supply_high_ratio: float = 1.125
    # values set on the built calibration, as XCP writes set them: ((name, values), ...), the
    # [calibration] table of a design file (calib.calpage; python -m hil xcp save writes one)
    calibration: tuple = ()


def load_options(path: str | Path, base: DesignOptions | None = None) -> DesignOptions:
    """``base`` (default: the defaults) with the ``[design]`` table of a TOML file applied,
    and its ``[calibration]`` table, if any (``calib.calpage``)."""
    from calib import calpage

    path = Path(path)
    data = read_toml(path, "design")
    unknown = set(data) - {"design", "calibration"}
    if unknown:
        raise ConfigError(f"{path}: unknown table or key '{sorted(unknown)[0]}' (only [design] "
                          f"and [calibration])")
    table = data.get("design", {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: 'design' must be a table")
    base = base or DesignOptions()
    fields = {f.name: f for f in dataclasses.fields(DesignOptions)}
    changes = {}
    for key, value in table.items():
        if key not in fields or key == "calibration":
            raise ConfigError(f"{path}: unknown key 'design.{key}'")
        changes[key] = _checked(path, key, value, getattr(base, key))
    if "calibration" in data:
        changes["calibration"] = calpage.check_table(path, data["calibration"])
    return dataclasses.replace(base, **changes)


def _checked(path: Path, key: str, value, default):
    where = f"{path}: key 'design.{key}'"
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if isinstance(default, tuple) and all(isinstance(v, bool) for v in default):
        if (not isinstance(value, list) or len(value) != len(default)
                or not all(isinstance(v, bool) for v in value)):
            raise ConfigError(f"{where} must be a list of {len(default)} booleans")
        return tuple(value)
    if isinstance(default, tuple):
        if (not isinstance(value, list) or len(value) != len(default)
                or not all(_is_number(v) and math.isfinite(v) and v > 0 for v in value)):
            raise ConfigError(f"{where} must be a list of {len(default)} positive numbers")
        return tuple(float(v) for v in value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ConfigError(f"{where} must be a non-negative integer, got {value!r}")
        return value
    if not _is_number(value) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"{where} must be a positive finite number, got {value!r}")
    return float(value)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)
