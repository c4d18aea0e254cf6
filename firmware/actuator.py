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
"""

from __future__ import annotations

from dataclasses import dataclass

from firmware.fixedpoint import round_half_away
from firmware.params import ActuatorParams, PlantParams

Q15_ONE = 32768
DUTY_MIN_Q15 = -32768
DUTY_MAX_Q15 = 32767
CURRENT_MARGIN = 0.95


@dataclass
class ActuatorState:
    integ: float = 0.0
    i_ref_prev: float = 0.0
    voltage: float = 0.0
    i_prev: float = 0.0
    observer_valid: bool = False
    emf: float = 0.0


def duty_to_q15(duty: float) -> int:
    return min(DUTY_MAX_Q15, max(DUTY_MIN_Q15, round_half_away(duty * Q15_ONE)))


def current_reference(plant: PlantParams, force: float, rel_vel: float, compensate: bool) -> float:
    demand = force + (plant.friction * rel_vel if compensate else 0.0)
    g = plant.efficiency if demand * rel_vel >= 0.0 else 1.0 / plant.efficiency
    i_ref = demand / (g * plant.force_constant)
    lim = CURRENT_MARGIN * plant.current_limit
    return min(lim, max(-lim, i_ref))


def step(params: ActuatorParams, plant: PlantParams, st: ActuatorState, i_ref: float,
         i_meas: float, rel_vel: float, regen: bool, min_ratio: float,
         rel_acc: float = 0.0, dt: float = 0.0) -> int:
    """Voltage for this tick from the current reference; returns the duty in Q15."""
    if st.observer_valid:
        emf = st.voltage - (i_meas - params.current_a * st.i_prev) / params.current_b
        emf += plant.force_constant * rel_acc * dt
    else:
        emf = plant.force_constant * (rel_vel + 0.5 * dt * rel_acc)
    st.emf = emf
    v_dc = plant.storage_voltage if regen else plant.bus_voltage
    # the integral learns the model error seen on the last tick's reference
    v_ff = emf + (i_ref - params.current_a * i_meas) / params.current_b
    v = v_ff + st.integ
    lo, hi = -v_dc, v_dc
    if regen:
        a, b = sorted((min_ratio * emf, emf))
        lo, hi = max(lo, a), min(hi, b)
    saturated = v < lo or v > hi
    v = min(hi, max(lo, v))
    if not saturated:
        st.integ += params.ki * (st.i_ref_prev - i_meas)
        st.integ = min(params.integ_limit, max(-params.integ_limit, st.integ))
    st.i_ref_prev = i_ref
    duty = duty_to_q15(v / v_dc)
    st.voltage = duty / Q15_ONE * v_dc      # what the bridge applies (quantised duty)
    st.i_prev = i_meas
    st.observer_valid = True
    return duty


def reset(st: ActuatorState) -> None:
    st.integ = 0.0
    st.i_ref_prev = 0.0
    st.voltage = 0.0
    st.observer_valid = False
