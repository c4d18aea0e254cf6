"""LQR and GA-LQR in fixed point: u = -K x (C: ``dot_state``, ``lqr_force``)."""

from __future__ import annotations

from firmware.fixedpoint import neg, sat32
from firmware.fx.tables import F_FORCE, STATE_FRAC, cm


def dot_state(ks: tuple, x: list) -> int:
    """K x, each product from the state's format to the force's."""
    return sat32(sum(cm(ks[j], x[j], STATE_FRAC[j], F_FORCE) for j in range(5)))


def force(ks: tuple, x: list) -> int:
    return neg(dot_state(ks, x))
