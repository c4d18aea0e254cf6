"""ISO 8608 road grades and the road PSD of the paper's Eq. (1) (errata 4, 5): the constants and
small functions both the calibration and the road generator use."""

from __future__ import annotations

import math

N0_PER_M = 0.1
"""Reference spatial frequency n0 of ISO 8608 (1/m)."""

GRADES = "ABCDEFGH"
GRADE_GQ_M3 = {g: 16e-6 * 4.0**i for i, g in enumerate(GRADES)}
"""Geometric-mean G_q(n0) of each ISO 8608 grade (m^3); bounds are x/2 and x2 of it."""

CONVENTIONS = {"iso": 0.5, "paper": 1.0}
DEFAULT_CUTOFF_N_PER_M = 0.005


def grade_of(gq_m3: float) -> str:
    """The ISO 8608 grade whose band [lower, upper) contains ``gq_m3`` (A below, H above)."""
    for grade in GRADES:
        if gq_m3 < 2.0 * GRADE_GQ_M3[grade]:
            return grade
    return GRADES[-1]


def gq_of(grade: str) -> float:
    try:
        return GRADE_GQ_M3[grade.upper()]
    except (KeyError, AttributeError):
        raise ValueError(f"unknown road grade {grade!r} (expected one of {', '.join(GRADES)})") from None


def convention_factor(convention: str) -> float:
    try:
        return CONVENTIONS[convention]
    except KeyError:
        raise ValueError(f"unknown PSD convention {convention!r} (expected 'iso' or 'paper')") from None


def road_noise_gain(gq_m3: float, speed_mps: float, convention: str = "iso") -> float:
    """Gain on unit-intensity white noise in time of Eq. (1) at constant speed:
    2*pi*n0*sqrt(kappa*G_q*v)."""
    return 2.0 * math.pi * N0_PER_M * math.sqrt(convention_factor(convention) * gq_m3 * speed_mps)


def road_intensity_per_mps(gq_m3: float, convention: str = "iso") -> float:
    """The intensity of the white noise driving the road state per m/s of speed:
    (2 pi n0)^2 kappa G_q (the square of ``road_noise_gain`` over the speed)."""
    return (2 * math.pi * N0_PER_M) ** 2 * CONVENTIONS[convention] * gq_m3
