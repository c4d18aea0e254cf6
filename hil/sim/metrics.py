"""Ride and road-holding metrics: RMS, ISO 2631-1 W_k weighted RMS, peaks, events."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def rms(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def peak(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.max(np.abs(x))) if x.size else float("nan")


def rising_edges(flags: np.ndarray) -> int:
    """Number of False -> True transitions (an event that starts in the first sample counts)."""
    f = np.asarray(flags, dtype=bool)
    if not f.size:
        return 0
    return int(f[0]) + int(np.count_nonzero(f[1:] & ~f[:-1]))


def wk_analog() -> tuple[np.ndarray, np.ndarray]:
    """ISO 2631-1 Annex A, weighting W_k (vertical, seated): band limiting (0.4 Hz high-pass,
    100 Hz low-pass, Q = 1/sqrt 2), acceleration-velocity transition (f3 = f4 = 12.5 Hz,
    Q4 = 0.63) and upward step (f5 = 2.37 Hz, Q5 = 0.91, f6 = 3.35 Hz, Q6 = 0.91).
    Returns (b, a) of the analogue transfer function in s."""
    w = [2 * math.pi * f for f in (0.4, 100.0, 12.5, 12.5, 2.37, 3.35)]
    q1, q4, q5, q6 = 1 / math.sqrt(2), 0.63, 0.91, 0.91
    hh = ([1.0, 0.0, 0.0], [1.0, w[0] / q1, w[0] ** 2])
    hl = ([w[1] ** 2], [1.0, w[1] / q1, w[1] ** 2])
    ht = ([w[3] ** 2 / w[2], w[3] ** 2], [1.0, w[3] / q4, w[3] ** 2])
    # H_s includes its gain (f5/f6)^2, so the numerator is monic like the denominator
    hs = ([1.0, w[4] / q5, w[4] ** 2], [1.0, w[5] / q6, w[5] ** 2])
    b, a = np.array([1.0]), np.array([1.0])
    for nb, na in (hh, hl, ht, hs):
        b, a = np.polymul(b, nb), np.polymul(a, na)
    return b, a


def wk_digital(fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear-transform W_k at sample rate ``fs_hz``."""
    from scipy.signal import bilinear_zpk, zpk2tf   # (here: its import takes half a second)

    b, a = wk_analog()
    z, p, k = np.roots(b), np.roots(a), b[0] / a[0]
    zd, pd, kd = bilinear_zpk(z, p, k, fs_hz)
    bd, ad = zpk2tf(zd, pd, kd)
    return np.real(bd), np.real(ad)


def wk_weighted_rms(accel_mps2: np.ndarray, fs_hz: float) -> float:
    from scipy.signal import lfilter

    b, a = wk_digital(fs_hz)
    return rms(lfilter(b, a, np.asarray(accel_mps2, dtype=float)))


@dataclass(frozen=True)
class RideMetrics:
    ba_rms_mps2: float
    sws_rms_m: float
    dtd_rms_m: float
    force_rms_n: float
    ba_wk_rms_mps2: float
    ba_peak_mps2: float
    sws_peak_m: float
    dtd_peak_m: float
    bump_stop_contacts: int
    tire_lift_off_events: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def ride_metrics(ba: np.ndarray, sws: np.ndarray, dtd: np.ndarray, force: np.ndarray,
                 fs_hz: float, bump_contact: np.ndarray | None = None,
                 lift_off: np.ndarray | None = None) -> RideMetrics:
    empty = np.zeros(0, dtype=bool)
    return RideMetrics(
        ba_rms_mps2=rms(ba), sws_rms_m=rms(sws), dtd_rms_m=rms(dtd), force_rms_n=rms(force),
        ba_wk_rms_mps2=wk_weighted_rms(ba, fs_hz),
        ba_peak_mps2=peak(ba), sws_peak_m=peak(sws), dtd_peak_m=peak(dtd),
        bump_stop_contacts=rising_edges(bump_contact if bump_contact is not None else empty),
        tire_lift_off_events=rising_edges(lift_off if lift_off is not None else empty),
    )
