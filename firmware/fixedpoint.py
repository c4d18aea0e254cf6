"""Fixed-point helpers: the integer arithmetic of the fixed-point control path, written so that
C99 with ``int32_t``/``int64_t`` computes the same bits (``c/ecu_fx.c`` mirrors every function).

Representation: a signal or constant is an ``int32`` mantissa ``m`` with ``f`` fractional bits,
value = m * 2^-f (Qm.f with m + f = 31; CMSIS's q31 is f = 31, q15 an int16 with f = 15).
Rules (docs/architecture.md, Conventions): round half away from zero, saturate, never wrap.

* ``mul(a, b, s)``: the int64 product a*b (|a*b| <= 2^62, no overflow), shifted right by
  ``s`` in [0, 62] with rounding half away from zero, saturated to int32.
* every add/sub saturates to int32; sums of products saturate each term, then the total
  (at most a few int32 terms: no int64 overflow).

Compiled (numba): the integer operations run inside the tick and from Python alike (the
calibration's table builders). ``cm``/``cmi`` are a table constant (a record with ``m`` and
``frac``) times a signal, from one format to another (C: ``CM``/``AM``). ``round_half_away``
and ``best_frac`` are the host's: they refuse a NaN or an infinity (the compiled tick's own
rounding is ``firmware.util.round_half_away``).
"""

from __future__ import annotations

import math

from firmware.kernels import njit
from firmware.util import round_half_away as _rha

INT32_MAX = 2 ** 31 - 1
INT32_MIN = -(2 ** 31)
INT16_MAX = 2 ** 15 - 1
INT16_MIN = -(2 ** 15)
MAX_SHIFT = 62

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
    """A finite float as a saturated int32 mantissa with ``frac`` fractional bits. Saturated
    before the conversion to an integer: compiled, a float beyond int64 does not convert
    (it wrapped to INT32_MIN where Python's integers saturate to INT32_MAX)."""
    y = v * 2.0 ** frac
    if y >= INT32_MAX + 0.5:
        return INT32_MAX
    if y <= INT32_MIN - 0.5:
        return INT32_MIN
    return _rha(y)


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


def round_half_away(x: float) -> int:
    """The project's one rounding rule for floats to integers (docs/architecture.md,
    Conventions): half away from zero. A NaN or an infinity raises ValueError (math.floor)."""
    return math.floor(x + 0.5) if x >= 0.0 else -math.floor(-x + 0.5)   # (floor gives an int)


def best_frac(v: float, lo: int = 0, hi: int = 46, headroom_bits: int = 0) -> int:
    """The most fractional bits (in [lo, hi]) with which |v| * 2^headroom fits an int32."""
    if not math.isfinite(v):
        raise ValueError(f"cannot represent {v!r} in fixed point")
    a = abs(v) * 2.0 ** headroom_bits
    f = hi
    while f > lo and round_half_away(a * 2.0 ** f) > INT32_MAX:
        f -= 1
    if round_half_away(a * 2.0 ** f) > INT32_MAX:
        raise ValueError(f"{v!r} does not fit an int32 with {lo} fractional bits")
    return f
