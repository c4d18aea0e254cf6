"""``firmware.fixedpoint``'s integer arithmetic, compiled (int64 intermediates, as C's
``int64_t``): round half away from zero, saturate, never wrap. ``cm``/``cmi`` are
``firmware.fx.tables.cm`` for a constant (a record with ``m`` and ``frac``) and for the
``i``-th of a table of them."""

from __future__ import annotations

import math

from firmware.fixedpoint import INT16_MAX, INT16_MIN, INT32_MAX, INT32_MIN
from firmware.kernels import njit
from firmware.tick.util import round_half_away


@njit
def sat32(x):
    return INT32_MAX if x > INT32_MAX else INT32_MIN if x < INT32_MIN else x


@njit
def sat16(x):
    return INT16_MAX if x > INT16_MAX else INT16_MIN if x < INT16_MIN else x


@njit
def rshift_round(p, s):
    """p / 2^s rounded half away from zero (p in int64, s in [0, 62])."""
    if s == 0:
        return p
    half = 1 << (s - 1)
    return (p + half) >> s if p >= 0 else -((half - p) >> s)


@njit
def mul(a, b, s):
    return sat32(rshift_round(a * b, s))


@njit
def add(a, b):
    return sat32(a + b)


@njit
def sub(a, b):
    return sat32(a - b)


@njit
def neg(a):
    return sat32(-a)


@njit
def clamp(x, lo, hi):
    return lo if x < lo else hi if x > hi else x


@njit
def div_round(a, n):
    """a / n rounded half away from zero, n > 0."""
    q = (abs(a) + n // 2) // n
    return q if a >= 0 else -q


@njit
def same_sign_or_zero(a, b) -> bool:
    return a == 0 or b == 0 or (a > 0) == (b > 0)


@njit
def to_fixed(v: float, frac: int) -> int:
    return sat32(round_half_away(v * 2.0 ** frac))


@njit
def to_float(m: int, frac: int) -> float:
    return m * 2.0 ** -frac


@njit
def cm(c, x, f_in, f_out):
    """The constant c times x, from format f_in to f_out (C: ``CM``)."""
    return mul(c.m, x, c.frac + f_in - f_out)


@njit
def cmi(c, i, x, f_in, f_out):
    """The i-th constant of table c times x (C: ``AM``)."""
    return mul(c.m[i], x, c.frac[i] + f_in - f_out)


@njit
def isfinite(v: float) -> bool:
    return math.isfinite(v)
