"""Skyhook in fixed point (C: ``skyhook_force``)."""

from __future__ import annotations

from firmware.fixedpoint import neg, sat32, sub
from firmware.fx.tables import F_FORCE, F_VEL, FxTables, cm


def force(T: FxTables, x: list) -> int:
    return neg(sat32(cm(T.skyhook_c, x[0], F_VEL, F_FORCE)
                     + cm(T.skyhook_passive_c, sub(x[0], x[1]), F_VEL, F_FORCE)))
