"""Actuator output stage: force command -> current reference -> H-bridge voltage -> PWM duty.

* Force to current: the screw delivers g K i - b v_rel with g = eta when the motor drives and
  1/eta when it is back-driven; the friction b is compensated in the active modes (not when
  harvesting, where it is free damping). The current reference is limited below the bridge's
  hardware limit.
* Current loop: deadbeat on the discrete winding model i' = a i + b_c (V - EMF), plus an
  integral correction of the model error with anti-windup (conditional integration and clamp).
  The EMF comes from a disturbance observer: last tick's voltage and the measured current
  response give the EMF that acted over it, EMF = V - (i_k - a i_{k-1}) / b_c (a far better
  velocity sensor than the state estimate), advanced by one tick with the relative
  acceleration. Without a valid last tick (bridge was off) the state estimate is used.
* Voltage to duty: saturate to the DC voltage (bus, or storage when the regen switch is on);
  duty in Q15, rounded half away from zero, saturated.
* Regeneration: the terminal voltage is kept between ``min_ratio`` * EMF and the EMF (same
  sign), where the current flows against the EMF and the power into the storage element.

Compiled (numba) over the state record's ``ctl.actuator`` fields.
"""

from __future__ import annotations

import numpy as np

from firmware.kernels import njit
from firmware.util import clamp, pymax, pymin, round_half_away

Q15_ONE = 32768
DUTY_MIN_Q15 = -32768
DUTY_MAX_Q15 = 32767

ACTUATOR = np.dtype([("integ", "f8"), ("i_ref_prev", "f8"), ("voltage", "f8"),
                     ("i_prev", "f8"), ("observer_valid", "u1"), ("emf", "f8")])


@njit
def current_reference(pl, act, force: float, rel_vel: float, compensate: bool) -> float:
    demand = force + (pl.friction * rel_vel if compensate else 0.0)
    g = pl.efficiency if demand * rel_vel >= 0.0 else 1.0 / pl.efficiency
    i_ref = demand / (g * pl.force_constant)
    lim = act.current_limit
    return clamp(i_ref, -lim, lim)


@njit
def duty_to_q15(duty: float) -> int:
    return pymin(DUTY_MAX_Q15, pymax(DUTY_MIN_Q15, round_half_away(duty * Q15_ONE)))


@njit
def step(A, pl, S, i_ref: float, i_meas: float, rel_vel: float, regen: bool,
                  min_ratio: float, rel_acc: float, dt: float) -> int:
    """Voltage for this tick from the current reference; returns the duty in Q15."""
    if S.observer_valid:
        emf = S.voltage - (i_meas - A.current_a * S.i_prev) / A.current_b
        emf += pl.force_constant * rel_acc * dt
    else:
        emf = pl.force_constant * (rel_vel + 0.5 * dt * rel_acc)
    S.emf = emf
    v_dc = pl.storage_voltage if regen else pl.bus_voltage
    # the integral learns the model error seen on the last tick's reference
    v_ff = emf + (i_ref - A.current_a * i_meas) / A.current_b
    v = v_ff + S.integ
    lo, hi = -v_dc, v_dc
    if regen:
        r = min_ratio * emf
        a, b = (emf, r) if emf < r else (r, emf)     # (sorted((r, emf)))
        lo, hi = pymax(lo, a), pymin(hi, b)
    saturated = v < lo or v > hi
    v = clamp(v, lo, hi)
    if not saturated:
        S.integ += A.ki * (S.i_ref_prev - i_meas)
        S.integ = clamp(S.integ, -A.integ_limit, A.integ_limit)
    S.i_ref_prev = i_ref
    duty = duty_to_q15(v / v_dc)
    S.voltage = duty / Q15_ONE * v_dc      # what the bridge applies (quantised duty)
    S.i_prev = i_meas
    S.observer_valid = True
    return duty


@njit
def reset(S) -> None:
    S.integ = 0.0
    S.i_ref_prev = 0.0
    S.voltage = 0.0
    S.observer_valid = False
