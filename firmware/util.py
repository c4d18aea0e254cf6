"""Small helpers of the compiled stages, with the semantics of the Python builtins they stand
for (where a NaN goes, which way a tie rounds)."""

from __future__ import annotations

import math

from firmware.kernels import njit


@njit
def pymax(a, b):
    """Python's ``max(a, b)``: ``b`` only where ``b > a`` (a NaN ``b`` never wins)."""
    return b if b > a else a


@njit
def pymin(a, b):
    """Python's ``min(a, b)``: ``b`` only where ``b < a``."""
    return b if b < a else a


@njit
def clamp(x, lo, hi):
    """Python's ``min(hi, max(lo, x))`` (a NaN ``x`` gives ``lo``)."""
    return pymin(hi, pymax(lo, x))


@njit
def round_half_away(x: float) -> int:
    """Half away from zero (``firmware.fixedpoint.round_half_away``, which refuses a NaN)."""
    return math.floor(x + 0.5) if x >= 0.0 else -math.floor(-x + 0.5)
