"""LQR state feedback u = -K x on the AKF's estimate: safety mode's gain (designed by
``calib.design``, LQR with BA and SWS bounded by the passive car's) and comprehensive mode's
GA-LQR gain (tuned by ``calib.galqr``, Eq. (43)/(44)). The firmware only applies the gain."""

from __future__ import annotations

import numpy as np


def force(k: np.ndarray, x: np.ndarray) -> float:
    return -float(k @ x)
