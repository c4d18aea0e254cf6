"""Stage 8's DTC memory, compiled (``firmware.diag.dtc`` says how ISO 14229's status bits,
debouncing, confirmation, aging and snapshots work here): one row per DTC of
``firmware.diag.dtc.DTCS``, in its order."""

from __future__ import annotations

import numpy as np

from firmware.diag.dtc import (AGING_CYCLES, CDTC, DTCS, FDC_MAX, FDC_MIN, MAX_OCCURRENCES, PASS_REPORTS,
                               PDTC, SRC_FAULT, STATUS_AFTER_CLEAR, STEP_UP, TF, TFSLC, TFTOC,
                               TNCSLC, TNCTOC, WIR)
from firmware.kernels import njit

N = len(DTCS)
SOURCE = np.array([d.source for d in DTCS], dtype=np.int64)
BIT = np.array([d.bit for d in DTCS], dtype=np.int64)
SAFETY = np.array([d.safety for d in DTCS], dtype=np.int64)
# the snapshot (record 1): firmware.diag.dtc.Snapshot's fields, in its order
SNAPSHOT = ("tick", "speed_cmps", "grade", "mode", "ba_rms_mmps2", "dtd_rms_um", "supply_mv")

STATE = np.dtype([
    ("status", "i8", (N,)), ("fdc", "i8", (N,)),
    ("passes", "i8", (N,)),            # passed reports in a row
    ("occurrences", "i8", (N,)),       # operation cycles with a failure since the last clear
    ("aging", "i8", (N,)),             # operation cycles passed without failure since then
    ("has_snapshot", "u1", (N,)), ("snapshot", "i8", (N, len(SNAPSHOT))),
    ("first_tick", "i8", (N,)),        # tick of the first failure this cycle
    ("setting_on", "u1"),              # 0x85 ControlDTCSetting
    ("cycle", "i8"),
    ("quiet", "u1"),                   # every entry at rest (no failure this cycle)
    ("tnc_done", "u1"),                # no not-completed bit left to clear
])


def init(S) -> None:
    S.setting_on = S.quiet = True
    clear_entries(S, np.arange(N))


def clear_entries(S, idx) -> None:
    for i in idx:
        S.status[i], S.fdc[i], S.first_tick[i] = STATUS_AFTER_CLEAR, FDC_MIN, -1
        S.passes[i] = S.occurrences[i] = S.aging[i] = S.has_snapshot[i] = 0
        S.snapshot[i, :] = 0
    S.quiet, S.tnc_done = True, False


@njit
def update(S, tick: int, fault_word: int, test_failed: int, test_completed: int,
           snapshot) -> None:
    """One tick of reports (``firmware.diag.dtc.update``); ``snapshot``: the freeze frame a
    first failure takes (SNAPSHOT's fields)."""
    if not S.setting_on:
        return
    if S.quiet and not fault_word and not test_failed:
        if not S.tnc_done:
            _complete_quiet(S, test_completed)
        return
    any_active = False
    for i in range(N):
        if SOURCE[i] == SRC_FAULT:
            fail, done = (fault_word & BIT[i]) != 0, True
        else:
            fail, done = (test_failed >> BIT[i]) & 1 != 0, (test_completed >> BIT[i]) & 1 != 0
        if fail:
            _failed(S, i, tick, snapshot)
        elif done:
            _passed(S, i)
        if S.status[i] & (TF | TFTOC) or S.fdc[i] > FDC_MIN:
            any_active = True
    S.quiet = not any_active


@njit
def _complete_quiet(S, completed: int) -> None:
    left = False
    for i in range(N):
        if S.status[i] & (TNCSLC | TNCTOC):
            if SOURCE[i] == SRC_FAULT or (completed >> BIT[i]) & 1:
                S.status[i] &= ~(TNCSLC | TNCTOC)
            else:
                left = True
    S.tnc_done = not left


@njit
def _failed(S, i: int, tick: int, snapshot) -> None:
    S.passes[i] = 0
    S.fdc[i] = min(FDC_MAX, S.fdc[i] + STEP_UP)
    S.status[i] &= ~(TNCSLC | TNCTOC)
    if S.fdc[i] >= FDC_MAX and not S.status[i] & TF:
        first_this_cycle = not S.status[i] & TFTOC
        S.status[i] |= TF | TFTOC | PDTC | CDTC | TFSLC
        if SAFETY[i]:
            S.status[i] |= WIR
        if first_this_cycle:
            S.occurrences[i] = min(MAX_OCCURRENCES, S.occurrences[i] + 1)
            S.aging[i] = 0
            S.first_tick[i] = tick
        if not S.has_snapshot[i]:
            S.has_snapshot[i] = True
            S.snapshot[i, :] = snapshot


@njit
def new_cycle(S) -> None:
    """A new operation cycle (``firmware.diag.dtc.new_cycle``): pending clears where the last
    cycle completed without failure, confirmed DTCs age, the this-cycle bits start again."""
    S.cycle += 1
    for i in range(N):
        failed = (S.status[i] & TFTOC) != 0
        completed = not S.status[i] & TNCTOC
        if completed and not failed:
            S.status[i] &= ~PDTC
            if S.status[i] & CDTC:
                S.aging[i] += 1
                if S.aging[i] >= AGING_CYCLES:
                    S.status[i] &= ~(CDTC | WIR)
                    S.aging[i] = 0
        S.status[i] &= ~(TFTOC | WIR | TF)
        S.status[i] |= TNCTOC
        S.fdc[i], S.passes[i], S.first_tick[i] = FDC_MIN, 0, -1
    S.quiet, S.tnc_done = True, False


@njit
def _passed(S, i: int) -> None:
    S.status[i] &= ~(TNCSLC | TNCTOC)
    S.passes[i] += 1
    S.fdc[i] = max(FDC_MIN, S.fdc[i] - (FDC_MAX - FDC_MIN) // PASS_REPORTS)
    if S.passes[i] >= PASS_REPORTS:
        S.fdc[i] = FDC_MIN
        S.status[i] &= ~TF
