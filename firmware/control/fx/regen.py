"""The energy-feedback damping law in fixed point (C: ``regen_force``): only dissipative
forces."""

from __future__ import annotations

from firmware.fixedpoint import neg, sat32, sub
from firmware.fx.tables import F_FORCE, F_VEL, FxTables, cm


def force(T: FxTables, x: list) -> int:
    rel = sub(x[0], x[1])
    f = neg(sat32(cm(T.regen_c, rel, F_VEL, F_FORCE) + cm(T.regen_skyhook_c, x[0], F_VEL, F_FORCE)))
    return 0 if (f > 0 and rel > 0) or (f < 0 and rel < 0) else f
