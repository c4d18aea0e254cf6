"""The calibration's grid: what a solver returns into a design rounded to 32 significant bits.

A design step that is solved to its true value still carries the host's rounding in its last
bits (about 1e-13 relative where a solve is ill-conditioned, ``calib.exact``). Rounded to a
grid far coarser than that, the same design gives the same bits on every host, except where a
value falls within that rounding of a grid boundary (about 1e-13 / 2.3e-10, a few in 10,000
per value). The grid of a number x in an array whose largest magnitude is a_max is
2^(e - ``SIGNIFICANT_BITS``) for x's binary exponent e, but never finer than
2^(e_max - ``FLOOR_BITS``) for a_max's: a value that is zero in exact arithmetic but comes
out as rounding (1e-34 of a covariance's largest entry) becomes exactly 0 instead of noise.
Relative to the largest entry the grid is at most 2^-40 (9e-13), below anything the ECU's
float path or its Q-formats resolve.
"""

from __future__ import annotations

import numpy as np

SIGNIFICANT_BITS = 32
FLOOR_BITS = 40


def snap(a):
    """``a`` (a number or an array) on the grid; an int, bool or non-finite value unchanged."""
    if isinstance(a, (bool, int, np.integer, np.bool_)):
        return a
    arr = np.asarray(a)
    if arr.dtype.kind != "f":
        return a
    x = np.asarray(arr, dtype=float)
    finite = np.isfinite(x)
    if not np.any(finite & (x != 0.0)):
        return a
    a_max = float(np.max(np.abs(x[finite])))
    _, e = np.frexp(np.where(finite, x, 0.0))
    e_max = np.frexp(a_max)[1]
    ex = np.maximum(e - SIGNIFICANT_BITS, e_max - FLOOR_BITS)
    # (+ 0.0: a value rounded to zero is +0, whatever its sign was: -0 and +0 are other bytes)
    out = np.where(finite, np.ldexp(np.round(np.ldexp(np.where(finite, x, 0.0), -ex)), ex) + 0.0,
                   x)
    if isinstance(a, float):
        return float(out)
    return np.ascontiguousarray(out, dtype=arr.dtype)

