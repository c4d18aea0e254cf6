"""Calibration of the ECU: every constant the firmware needs, as plain numbers and arrays.

Built offline (``calib.ecu_params``) from the vehicle file, the design tools and the gains file;
the firmware never reads files itself. The same values are exported as C tables.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Modes (values are the ones on the bus)
MODE_PASSIVE = 0
MODE_ENERGY = 1          # energy feedback (regeneration), paper's "feedthrough mode" (errata 10)
MODE_COMFORT = 2
MODE_SAFETY = 3
MODE_COMPREHENSIVE = 4
MODE_NAMES = ("passive", "energy", "comfort", "safety", "comprehensive")

# Controllers
CTRL_NONE = 0
CTRL_PID = 1
CTRL_BPPID = 2
CTRL_LQR = 3
CTRL_GALQR = 4
CTRL_SKYHOOK = 5
CTRL_REGEN = 6
CTRL_NAMES = ("none", "pid", "bppid", "lqr", "galqr", "skyhook", "regen")

# Grades A..D as 0..3 (D stands for D and rougher, as in the paper)
GRADE_NAMES = "ABCD"
GRADE_UNKNOWN = 255

# Driver request kinds
REQ_NONE = 0
REQ_ACCEPT = 1     # accept the recommendation whose mode is in the request
REQ_REFUSE = 2     # refuse the current recommendation
REQ_CHOOSE = 3     # choose a mode explicitly


@dataclass(frozen=True)
class AdcChannel:
    range_min: float
    lsb: float
    full_scale: int          # highest count (2^bits - 1)


@dataclass(frozen=True)
class AdcParams:
    body_accel: AdcChannel
    wheel_accel: AdcChannel
    susp_defl: AdcChannel
    motor_current: AdcChannel
    speed: AdcChannel
    rail_ticks: int          # consecutive samples at a rail that make a channel faulty
    recover_ticks: int       # consecutive good samples that clear the fault (hysteresis)
    # relative velocity (m/s) beyond which the back-EMF alone drives the motor current past its
    # sensor's range: the current at a rail is then a measurement beyond the range, not a
    # fault (inf: never)
    current_rail_mps: float = float("inf")
    # the deflection sensor's rail is explained while the last estimate's stroke is within
    # this (m) of it or beyond (the stroke really is at the end of the sensor's range)
    defl_rail_margin_m: float = 0.0


@dataclass(frozen=True)
class PlantParams:
    """What the ECU knows of the corner (for the model-based parts)."""

    ms: float
    mt: float
    ks: float
    cs: float
    kt: float
    friction: float          # screw viscous friction (N s/m)
    force_constant: float    # N/A, also V/(m/s)
    efficiency: float
    resistance: float
    inductance: float
    current_limit: float
    bus_voltage: float
    storage_voltage: float


@dataclass(frozen=True)
class AkfParams:
    phi: np.ndarray          # (5,5) state transition at the ECU tick
    gamma: np.ndarray        # (5,)  known force input (ZOH)
    q_unit: np.ndarray       # (5,5) discrete process noise per unit road intensity (m^2/s^3)
    road_intensity_per_mps: float  # (2 pi n0)^2 kappa G_q,nominal: times speed = road intensity
    H: np.ndarray            # (m,5) measurement matrix
    D: np.ndarray            # (m,)  force feedthrough
    r0: np.ndarray           # (m,m) a-priori measurement noise
    r_floor: np.ndarray      # (m,)  floor of R-hat eigenvalues (guard)
    forgetting: float        # b of Eq. (15)/(16)
    adaptive: bool
    bias_adaptive: bool      # estimate r-hat (Eq. 15)
    p0: np.ndarray           # (5,5) initial covariance
    # Where the linear model does not hold (docs/ecu.md, "The estimator off the linear
    # model"): the bump stops are a known force from the measured stroke; an airborne tyre
    # and a current beyond its sensor's range are unknown forces, added as process noise.
    bump_clearance_m: float = 0.0    # stroke at which the bump stops act ...
    bump_stiffness: float = 0.0      # ... and their stiffness (N/m; 0: no bump stops)
    gamma_wheel: np.ndarray | None = None  # (5,) a force on the wheel alone (ZOH)
    tyre_load_n: float = 0.0         # static tyre load
    tyre_force_sigma_n: float = 0.0  # noise of the tyre force measured as load + ms BA + mt WA
    lift_sigmas: float = 5.0         # airborne: the measured tyre force below this many sigma
    lift_force_sigma_n: float = 0.0  # std of the unknown wheel force while airborne (0: the
    #                                  vehicle's tyre cannot lift off)
    current_force_sigma_n: float = 0.0  # std of the unknown actuator force while the current
    #                                     sensor is at a rail or faulty
    stroke_force_sigma_n: float = 0.0   # ... and of the bump stops' force while the stroke
    #                                     sensor is (0: no bump stops)


@dataclass(frozen=True)
class GradeParams:
    classifier: int          # 0 = road-estimate classifier (default), 1 = paper's threshold rule
    hp_a: float              # 1st-order high-pass on the road velocity estimate
    lp_a: float              # 1st-order low-pass
    block_ticks: int         # variance blocks
    n_blocks: int            # blocks in the window
    speed_grid: np.ndarray   # m/s
    var_per_gq: np.ndarray   # band variance per unit G_q at each grid speed (m^2/s^2 / m^3)
    gq_centres: np.ndarray   # geometric-mean G_q of A..D
    hysteresis: float        # in grade units (log4 of G_q)
    dwell_ticks: int         # a new grade must persist this long
    min_speed: float         # below this the estimate freezes
    dtd1: float              # paper thresholds, Eq. (24)-(26)
    ba1: float
    ba2: float


@dataclass(frozen=True)
class ModeParams:
    ramp_ticks: int              # bumpless transfer duration
    safety_dtd_rms_limit: float  # road-holding limit on the tyre deflection RMS (m)
    safety_exit_ratio: float     # leave the override below limit * ratio
    safety_window_ticks: int     # RMS window of the road-holding check
    safety_hold_ticks: int       # minimum time in the override
    initial_mode: int
    controllers: tuple[int, ...]  # controller of each mode (index = mode)
    request_min_ticks: int = 250  # a new driver request sooner than this after the previous
    #                               new one is ignored and flagged (request spam)


@dataclass(frozen=True)
class ControlParams:
    k_safety: np.ndarray         # (5,) u = -K x_hat
    k_comprehensive: np.ndarray  # (5,) GA-LQR
    k_comfort: np.ndarray        # (5,) comfort: state feedback under the BP-PID
    skyhook_c: float             # N s/m on body velocity
    skyhook_passive_c: float     # N s/m on relative velocity (added damping)
    pid_kp: float                # N per m/s^2 of BA error
    pid_ki: float                # N per m/s of integrated BA error
    pid_kd: float                # N per m/s^3
    pid_leak: float              # per-tick leak of the incremental PID output
    bp_w_hidden: np.ndarray      # (5,4) initial hidden weights (bias column last input x4 = 1)
    bp_b_hidden: np.ndarray      # (5,)
    bp_w_out: np.ndarray         # (3,5)
    bp_b_out: np.ndarray         # (3,)
    bp_eta: float                # learning rate
    bp_alpha: float              # momentum
    bp_scale: np.ndarray         # (3,) K_p, K_i, K_d = scale * g(net)
    bp_input_scale: float        # BA normalisation for the network inputs
    bp_gain_alpha: float         # per tick: the PID's gains low-pass the network's by this
    regen_c: float               # harvesting damping on relative velocity (N s/m)
    regen_skyhook_c: float       # skyhook part of the regen law (N s/m)
    regen_min_voltage_ratio: float  # keep |V| >= ratio*|EMF| so power flows into storage
    force_limit: float           # |F| command limit (N)


@dataclass(frozen=True)
class ActuatorParams:
    current_a: float             # discrete current pole exp(-R dt / L)
    current_b: float             # (1 - a) / R
    ki: float                    # integral gain of the current loop (V per A per tick)
    integ_limit: float           # anti-windup clamp of the integral (V)
    current_limit: float         # the loop's current limit (A): a margin x the winding's


@dataclass(frozen=True)
class EcuParams:
    dt_s: float
    adc: AdcParams
    plant: PlantParams
    akf: AkfParams
    grade: GradeParams
    modes: ModeParams
    control: ControlParams
    actuator: ActuatorParams
    akf_q_follows_grade: bool    # AKF road intensity from the grade estimate
    akf_q_gq_nominal: float      # the G_q behind akf.road_intensity_per_mps
    fdi: "FdiParams"             # model-based fault detection
    bank: "BankParams"           # the isolation bank (firmware.diag.bank)
    degrade: "DegradeParams"     # degraded operation (firmware.diag.degrade)
    software_version: str = "0.1.0"   # DID 0xF195
    calibration_sha256: bytes = bytes(32)  # DID 0xF1A0 (the C tables header's hash)
    vehicle_sha256: bytes = bytes(32)      # DID 0xF1A1


@dataclass(frozen=True)
class FdiParams:
    """Model-based fault detection (``firmware.diag.fdi``); derivations in docs/diagnostics.md."""

    nis_lambda: float            # EWMA weight of the windowed normalised innovation (2/(W+1))
    nis_threshold: float         # chi2_W(1 - alpha) / W: the windowed NIS alarm level
    flat_ticks: tuple[int, ...]  # identical counts in a row that mean stuck (BA, WA, SWS, I;
    #                              0: no flatline test, the channel's noise is below one LSB)
    force_band: float            # (1/eta - eta): the force-from-current ambiguity, per N
    valid_defl_m: float          # linear model valid below this |SWS| (the bump-stop clearance)
    hold_ticks: int              # after the model was invalid, the innovation tests wait this long
    cur_sigma_a: float           # current measurement noise (noise and quantisation), A
    act_var: float               # the actuator residual's variance from the current noise, A^2
    act_lambda: float            # EWMA weight of the actuator test ...
    act_threshold: float         # ... and its alarm level (chi2 quantile / window)
    act_confirm_ticks: int       # above the level this long (a supply sample in between)
    act_retry_ticks: int         # a failed actuator test holds this long, then retries
    act_flat_ticks: tuple[int, int]  # no actuator verdict while BA, WA repeat a count this often
    open_ratio: float            # open winding: |i| below this many sigma throughout
    supply_offset_v: float       # the supply voltage's ADC: volts at count 0 ...
    supply_lsb_v: float          # ... per count ...
    supply_full_scale: int       # ... and its full scale
    supply_change_v: float       # a sample this far from the last: the supply changed
    supply_low_v: float          # the operating range of the supply
    supply_high_v: float
    settle_ticks: int            # no test verdict before this tick (estimator start-up)
    clip_sq: float               # a normalised square enters the EWMAs at most this large
    nis_verdicts: tuple[bool, ...]  # which innovation tests report (BA, SWS, WA)
    actuator_verdicts: bool      # the actuator test reports (off: it runs, never fails)


@dataclass(frozen=True)
class BankParams:
    """The isolation bank (``firmware.diag.bank``; ``calib.fdi_bank``): four fixed-gain
    filters on the winding model, filter k blind to sensor k (BA, WA, SWS, current)."""

    phi: np.ndarray              # (4, 7, 7) state transition per filter
    phi_open: np.ndarray         # (4, 7, 7) ... with the bridge open (no winding current)
    gamma: np.ndarray            # (4, 7) the applied voltage's way in
    gamma_force: np.ndarray      # (4, 7) a force's way in (the screw efficiency's correction)
    D_force: np.ndarray          # (4, 3) ... and into the accelerations read
    H: np.ndarray                # (4, 3, 7) measurement rows
    K: np.ndarray                # (4, 7, 3) steady-state gains
    reads: tuple[int, ...]       # 4 x 3: the channels each reads (0 BA, 1 SWS, 2 WA, 3 current)
    S_road: np.ndarray           # (4, 3, 3) innovation covariance per unit road intensity
    S_noise: np.ndarray          # (4, 3, 3) ... from the sensor and voltage noise
    S_force: np.ndarray          # (4, 3, 3) ... per N^2 of a white force error
    K_open: np.ndarray           # (4, 7, 3) the gains with the bridge open (rows 5, 6 zero)
    S_road_open: np.ndarray      # (4, 3, 3) ... and their innovation covariance
    S_noise_open: np.ndarray     # (4, 3, 3)
    lam: float                   # the tests' EWMA weight ...
    level: float                 # ... and level: chi2_{3W}(1 - alpha) / (3W)
    confirm_ticks: int           # a sensor left alone this long is named
    act_ticks: int               # the actuator test's conclusion stands after this long
    decide_ticks: int            # else "not isolated" this long after the detection


@dataclass(frozen=True)
class DegradeParams:
    """Degraded operation (``firmware.diag.degrade``): the virtual sensor of each channel and
    the modes kept without each sensor."""

    H: np.ndarray                # (3, 5) the model's output of BA, WA, SWS (ADC order) ...
    D: np.ndarray                # (3,) ... and its force feedthrough
    modes: tuple[int, ...]       # per sensor out (BA, WA, SWS, current): bits of the modes kept
    readmit_ticks: int           # a sensor out that agrees again this long is used again ...
    readmissions: int            # ... this often per operation cycle (then it stays out)
