"""Energy-feedback mode: the motor as a generator.

The desired force is a damping law (harvesting damping on the relative velocity plus a skyhook
part on the body velocity). Only dissipative forces can be harvested, so a force that would
have to push (F * v_rel > 0) is dropped to zero: a semi-active law. The actuator stage then sets
the regen duty so that the terminal voltage stays between ``min_voltage_ratio`` times the EMF
and the EMF, where power flows into the storage element.
"""

from __future__ import annotations

from firmware.params import ControlParams


def force(p: ControlParams, body_vel: float, rel_vel: float) -> float:
    f = -p.regen_c * rel_vel - p.regen_skyhook_c * body_vel
    if f * rel_vel > 0.0:
        return 0.0
    return f
