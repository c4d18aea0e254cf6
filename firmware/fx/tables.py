"""The fixed-point path's formats and its constants' type (``FxTables``).

Formats (fractional bits of the int32 signals, the ``F_*`` constants): accelerations Q11.20,
velocities Q7.24, displacements Q3.28, forces Q19.12, currents and voltages Q11.20, jerk Q19.12,
network activations Q7.24, network weights and deltas Q3.28; the duty is Q15 (int16).
A constant is a mantissa with its own fractional bits (``Fx``), chosen offline
(``calib.fx_tables``) for the most precision that fits; a product c*x in format f_x to format
f_y shifts by f_c + f_x - f_y (``cm``, C's ``CM``/``AM`` macros).
"""

from __future__ import annotations

from dataclasses import dataclass


F_ACC = 20
F_VEL = 24
F_POS = 28
F_FORCE = 12
F_CUR = 20
F_VOLT = 20
F_JERK = 12
F_NN = 24
F_W = 28
F_TANH = 30
TANH_STEP_BITS = 7          # LUT step 2^-7 over [0, 8]
TANH_N = 8 << TANH_STEP_BITS
STATE_FRAC = (F_VEL, F_VEL, F_POS, F_POS, F_POS)
MEAS_FRAC = (F_ACC, F_POS, F_ACC)          # z = [BA, SWS, WA][:m]
ADC_FRAC = (F_ACC, F_ACC, F_POS, F_CUR)    # body accel, wheel accel, deflection, current
GAIN_HEADROOM_BITS = 8
ONE_NN = 1 << F_NN


@dataclass(frozen=True)
class Fx:
    """A constant: value = m * 2^-frac."""

    m: int
    frac: int
    value: float              # the float it stands for (for the tables and the docs)

    def shift(self, f_in: int, f_out: int) -> int:
        return self.frac + f_in - f_out


@dataclass(frozen=True)
class FxTables:
    n_meas: int
    adc_off: tuple            # 4 x Fx at the signal formats (ADC_FRAC)
    adc_lsb: tuple            # 4 x Fx (counts -> signal)
    phi: tuple                # 25 x Fx, row-major
    gamma: tuple              # 5 x Fx (force -> state)
    h: tuple                  # m*5 x Fx (state -> measurement)
    d: tuple                  # m x Fx (force -> measurement)
    k_frac: tuple             # m*5 fractional bits of the handed-over gain K (row-major 5 x m)
    bias_adaptive: bool
    bump_clear: Fx            # F_POS: the bump stops' clearance
    bump_k: Fx                # pos -> force: their stiffness (0: no bump stops)
    kf_eta: Fx                # current -> force, motoring
    kf_over_eta: Fx           # current -> force, back-driven
    inv_eta_kf: Fx            # force -> current
    eta_over_kf: Fx
    friction: Fx              # vel -> force
    current_limit: Fx         # F_CUR
    inv_mass: Fx              # force -> acc: 1/ms + 1/mt
    cur_a: Fx                 # current -> current
    inv_cur_b: Fx             # current -> voltage
    cur_ki: Fx                # current -> voltage
    integ_limit: Fx           # F_VOLT
    kf_dt: Fx                 # acc -> voltage
    kf: Fx                    # vel -> voltage
    half_dt: Fx               # acc -> vel
    v_bus: Fx                 # F_VOLT
    v_storage: Fx
    duty_per_v_bus: Fx        # voltage -> duty counts (frac 0)
    duty_per_v_storage: Fx
    regen_min_ratio: Fx       # voltage -> voltage
    k_safety: tuple           # 5 x Fx state -> force
    k_comprehensive: tuple
    k_comfort: tuple          # under the BP-PID
    skyhook_c: Fx             # vel -> force
    skyhook_passive_c: Fx
    regen_c: Fx
    regen_skyhook_c: Fx
    force_limit: Fx           # F_FORCE
    f_kp: int                 # formats of the PID gains (plain and network-tuned)
    f_ki: int
    f_kd: int
    pid_kp: Fx                # at f_kp
    pid_ki: Fx
    pid_kd: Fx
    pid_leak: Fx              # force -> force
    dt: Fx                    # acc -> vel
    inv_dt: Fx                # acc -> jerk
    bp_w_hidden: tuple        # 20 x Fx at F_W (5 x 4)
    bp_b_hidden: tuple        # 5
    bp_w_out: tuple           # 15 (3 x 5)
    bp_b_out: tuple           # 3
    bp_eta: Fx                # delta -> delta
    bp_alpha: Fx              # weight -> weight
    bp_scale: tuple           # 3 x Fx nn -> gain formats
    bp_inv_input_scale: Fx    # acc -> nn
    bp_gain_alpha: Fx         # gain -> gain (each gain's own format)
    bp_du_scale: tuple        # 3 x Fx: scale_l / FORCE_REF_N, du/dK_l (acc, vel, jerk) -> nn
    tanh_lut: tuple           # TANH_N + 1 ints at F_TANH
    ramp_ticks: int
    controllers: tuple
