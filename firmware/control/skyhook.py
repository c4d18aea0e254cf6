"""Skyhook damping: a force against the body velocity, plus optional added damping on the
relative velocity (x = [zs', zt', zs, zt, zf])."""

from __future__ import annotations

import numpy as np

from firmware.params import ControlParams


def force(p: ControlParams, x: np.ndarray) -> float:
    return -p.skyhook_c * x[0] - p.skyhook_passive_c * (x[0] - x[1])
