"""One tick's inputs of the fixed-point path as the C parity trace carries them (C:
``fx_in_t``); the ECU's record gives them with the tick's outputs
(``firmware.ecu.Ecu.fx_tick``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TickIn:
    """Everything the fixed-point path takes in one tick (a line of the parity trace; C:
    ``fx_in_t``)."""

    counts: tuple         # 4 x int or None
    k_q: tuple            # 5*m gain mantissas
    r_q: tuple            # m bias mantissas
    want: int
    passive: bool
    fault: bool
    regen: bool
    reset: bool = False   # the float supervisor reset the estimate (non-finite covariance)
    # what the covariance side took in and gave (the C estimator's replay, c/akf_cov.h):
    q_road: float = 0.0   # the road's process-noise intensity
    cov_flags: int = 0    # firmware.akf.COV_ bits
    k_f: tuple = ()       # the float gain (5*m), row-major
