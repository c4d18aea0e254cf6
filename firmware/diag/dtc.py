"""The DTC memory, ISO 14229-1 style (annex D): one DTC per detectable fault, its status byte,
counter-based debouncing, confirmation, aging and a snapshot at the first failure.

Status bits: 0 testFailed, 1 testFailedThisOperationCycle, 2 pendingDTC, 3 confirmedDTC,
4 testNotCompletedSinceLastClear, 5 testFailedSinceLastClear, 6
testNotCompletedThisOperationCycle, 7 warningIndicatorRequested (confirmed and
safety-relevant, while failing or until the cycle ends).

Each tick every monitor reports failed, passed or nothing (not completed). Debounce (the
AUTOSAR Dem counter): the fault detection counter FDC moves by ``step_up`` on a failed report
and ``-step_down`` on a passed one, within [-128, 127]; testFailed is set at 127 and cleared at
-128. The monitors here are already statistical tests (or frame checks that act within the
tick), so a DTC is set by its first failed report (a frame timeout by ``TIMEOUT_DEBOUNCE``
in a row: it is stored only when it persists); a pass must be seen
``PASS_REPORTS`` times in a row to clear. Confirmation: at the first failed operation cycle
(threshold 1). Aging: a confirmed DTC whose test passed in ``AGING_CYCLES`` operation cycles
without failing is cleared from memory. The snapshot (record 1) is taken when testFailed is
first set since the last clear. The memory survives ``new_cycle`` (ECU reset, power cycle):
it stands for the ECU's non-volatile memory.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from firmware import adc, safety
from firmware.diag import fdi
from firmware.kernels import njit

TF, TFTOC, PDTC, CDTC, TNCSLC, TFSLC, TNCTOC, WIR = (1 << i for i in range(8))
AVAILABILITY_MASK = 0xFF                 # every bit is supported
STATUS_AFTER_CLEAR = TNCSLC | TNCTOC     # 0x50
FDC_MAX, FDC_MIN = 127, -128
STEP_UP = 255                            # one failed report sets testFailed
PASS_REPORTS = 2                         # passed reports in a row that clear it
# a frame timeout is a DTC only when it persists: this many ticks in a row with the timeout
# bit (10 ms without sensor data). The fail-safe reacts to the first (the fault word); a
# late or single lost frame (a loaded bench host: 1-3 in a row here) is a timing event
# the status reports, not a stored U0401-87
TIMEOUT_DEBOUNCE = 10
AGING_CYCLES = 40
MAX_OCCURRENCES = 255


class Dtc(NamedTuple):
    code: int            # 3 bytes: the 2-byte SAE J2012 code and its failure type byte
    name: str
    source: int          # where its reports come from: SRC_FAULT (a fault word bit) or SRC_TEST
    bit: int             # the fault bit, or the fdi test index
    safety: bool         # safety-relevant (warning indicator, fail-safe)
    what: str
    debounce: int = 1    # failed reports in a row that set testFailed (each: STEP_UP / this)

    @property
    def part(self) -> str:
        """The part this DTC tells a technician to look at: a sensor (``ba``, ``wa``,
        ``defl``, ``current``, ``speed``), ``actuator``, ``supply``, ``network`` (a frame or
        a message), ``ecu`` (its estimator); "" where it names none (not isolated)."""
        return next((part for prefix, part in _PART if self.name.startswith(prefix)), "")


# the parts a technician replaces (a DTC naming one of them wrongly is a wrong isolation)
PARTS = ("ba", "wa", "defl", "current", "speed", "actuator", "supply")
# a DTC's part by the prefix of its name (Dtc.part); sensor_not_isolated names none
_PART = (("body_accel", "ba"), ("wheel_accel", "wa"), ("susp_defl", "defl"),
         ("motor_current", "current"), ("speed", "speed"), ("actuator", "actuator"),
         ("supply", "supply"), ("estimator", "ecu"), ("frame", "network"),
         ("unknown_id", "network"), ("bus_rate", "network"), ("authentication", "network"),
         ("invalid_request", "network"))


SRC_FAULT, SRC_TEST = 0, 1


def _c(letter: str, number: int, ftb: int) -> int:
    """SAE J2012 'C1001' + failure type byte -> the 3-byte DTC (P 00, C 01, B 10, U 11)."""
    return (("PCBU".index(letter) << 14 | number) << 8) | ftb


_CH = adc.FAULT_BIT
DTCS = (
    # sensor circuits (ADC: out of range, stuck at a rail, no valid sample): FTB 0x1C
    Dtc(_c("C", 0x1001, 0x1C), "body_accel_circuit", SRC_FAULT, _CH["body_accel"], True,
        "body accelerometer: out of range, stuck at a rail or no sample"),
    Dtc(_c("C", 0x1002, 0x1C), "wheel_accel_circuit", SRC_FAULT, _CH["wheel_accel"], True,
        "wheel accelerometer: out of range, stuck at a rail or no sample"),
    Dtc(_c("C", 0x1003, 0x1C), "susp_defl_circuit", SRC_FAULT, _CH["susp_defl"], True,
        "deflection sensor: out of range, stuck at a rail or no sample"),
    Dtc(_c("C", 0x1004, 0x1C), "motor_current_circuit", SRC_FAULT, _CH["motor_current"], True,
        "motor current sensor: out of range, stuck at a rail or no sample"),
    Dtc(_c("C", 0x1005, 0x1C), "speed_circuit", SRC_FAULT, _CH["speed"], True,
        "vehicle speed: out of range or no valid frame"),
    # plausibility against the model: FTB 0x29 signal invalid. The innovation tests detect;
    # the isolation bank names the sensor (firmware.diag.bank), or says it cannot
    Dtc(_c("C", 0x1001, 0x29), "body_accel_plausibility", SRC_TEST, fdi.T_ISO_BA, True,
        "body accelerometer disagrees with the model (isolated by the filter bank)"),
    Dtc(_c("C", 0x1003, 0x29), "susp_defl_plausibility", SRC_TEST, fdi.T_ISO_SWS, True,
        "deflection sensor disagrees with the model (isolated by the filter bank)"),
    Dtc(_c("C", 0x1002, 0x29), "wheel_accel_plausibility", SRC_TEST, fdi.T_ISO_WA, True,
        "wheel accelerometer disagrees with the model (isolated by the filter bank)"),
    Dtc(_c("C", 0x1004, 0x29), "motor_current_plausibility", SRC_TEST, fdi.T_ISO_CUR, True,
        "motor current sensor disagrees with the model (isolated by the filter bank)"),
    Dtc(_c("C", 0x1000, 0x29), "sensor_not_isolated", SRC_TEST, fdi.T_NOT_ISOLATED, True,
        "a sensor disagrees with the model and the filter bank cannot tell which"),
    # stuck in range (flatline): FTB 0x2A
    Dtc(_c("C", 0x1001, 0x2A), "body_accel_stuck", SRC_TEST, fdi.T_FLAT_BA, True,
        "body accelerometer stuck at one count"),
    Dtc(_c("C", 0x1002, 0x2A), "wheel_accel_stuck", SRC_TEST, fdi.T_FLAT_WA, True,
        "wheel accelerometer stuck at one count"),
    Dtc(_c("C", 0x1003, 0x2A), "susp_defl_stuck", SRC_TEST, fdi.T_FLAT_SWS, True,
        "deflection sensor stuck at one count"),
    Dtc(_c("C", 0x1004, 0x2A), "motor_current_stuck", SRC_TEST, fdi.T_FLAT_CUR, True,
        "motor current sensor stuck at one count"),
    # actuator: FTB 0x71 actuator stuck, 0x13 circuit open
    Dtc(_c("C", 0x1010, 0x71), "actuator_stuck", SRC_TEST, fdi.T_NAME_ACT_STUCK, True,
        "the motor current does not follow the commanded voltage"),
    Dtc(_c("C", 0x1010, 0x13), "actuator_open", SRC_TEST, fdi.T_NAME_ACT_OPEN, True,
        "no motor current where the commanded voltage drives one (open winding)"),
    # the supply voltage: U3003 (battery voltage), FTB 0x16 below, 0x17 above the threshold
    Dtc(_c("U", 0x3003, 0x16), "supply_voltage_low", SRC_TEST, fdi.T_SUPPLY_LOW, True,
        "the supply voltage is below its operating range"),
    Dtc(_c("U", 0x3003, 0x17), "supply_voltage_high", SRC_TEST, fdi.T_SUPPLY_HIGH, True,
        "the supply voltage is above its operating range"),
    # the estimator: FTB 0x92 performance
    Dtc(_c("C", 0x1020, 0x92), "estimator_reset", SRC_FAULT, safety.FAULT_NONFINITE_ESTIMATE,
        True, "the state estimate diverged and was reset"),
    # network (U codes): 0x81 invalid data, 0x82 counter, 0x83 checksum, 0x87 missing
    Dtc(_c("U", 0x0401, 0x87), "frame_timeout", SRC_FAULT, safety.FAULT_TIMEOUT, True,
        "a sensor frame missing or VEHICLE_SPEED late", TIMEOUT_DEBOUNCE),
    Dtc(_c("U", 0x0401, 0x83), "frame_checksum", SRC_FAULT, safety.FAULT_CHECKSUM, True,
        "a frame with a bad CHECKSUM"),
    Dtc(_c("U", 0x0401, 0x82), "frame_counter", SRC_FAULT, safety.FAULT_COUNTER, True,
        "a frame's COUNTER repeated or jumped"),
    Dtc(_c("U", 0x0401, 0x81), "frame_dlc", SRC_FAULT, safety.FAULT_DLC, True,
        "a frame with the wrong DLC"),
    Dtc(_c("U", 0x0401, 0x86), "frame_range", SRC_FAULT, safety.FAULT_RANGE, True,
        "a signal outside its declared range"),
    Dtc(_c("U", 0x0402, 0x81), "unknown_id", SRC_FAULT, safety.FAULT_UNKNOWN_ID, False,
        "a frame with an ID the DBC does not define"),
    Dtc(_c("U", 0x0403, 0x81), "bus_rate", SRC_FAULT, safety.FAULT_RATE, False,
        "a message or driver request came too often"),
    Dtc(_c("U", 0x0404, 0x84), "authentication", SRC_FAULT, safety.FAULT_AUTH, False,
        "a secured message failed its SecOC check"),
    Dtc(_c("U", 0x0405, 0x81), "invalid_request", SRC_FAULT, safety.FAULT_INVALID_REQUEST,
        False, "a driver request for a mode that does not exist"),
)
BY_CODE = {d.code: i for i, d in enumerate(DTCS)}
BY_NAME = {d.name: i for i, d in enumerate(DTCS)}


class Snapshot(NamedTuple):
    """Record 1, taken at the first failure since the last clear (DID 0x0200's layout)."""

    tick: int
    speed_cmps: int          # vehicle speed, cm/s (0xFFFF unknown)
    grade: int               # 0..3 = A..D, 255 unknown
    mode: int                # active mode
    ba_rms_mmps2: int
    dtd_rms_um: int
    supply_mv: int           # DC supply voltage, mV (0xFFFF: not measured)


N = len(DTCS)
SOURCE = np.array([d.source for d in DTCS], dtype=np.int64)
BIT = np.array([d.bit for d in DTCS], dtype=np.int64)
SAFETY = np.array([d.safety for d in DTCS], dtype=np.int64)
# the FDC's step on a failed report: ``debounce`` of them in a row reach FDC_MAX from FDC_MIN
STEP = np.array([-(-STEP_UP // d.debounce) for d in DTCS], dtype=np.int64)
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
    """The rows ``idx`` as after a clear (the status 0x50, no snapshot, counters at rest)."""
    for i in idx:
        S["status"][i], S["fdc"][i], S["first_tick"][i] = STATUS_AFTER_CLEAR, FDC_MIN, -1
        S["passes"][i] = S["occurrences"][i] = S["aging"][i] = S["has_snapshot"][i] = 0
        S["snapshot"][i, :] = 0
    S["quiet"], S["tnc_done"] = True, False


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
    S.fdc[i] = min(FDC_MAX, S.fdc[i] + STEP[i])
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


def clear(mem, group: int) -> bool:
    """ClearDiagnosticInformation on the memory's view (``firmware.diag.view.MemoryView``,
    between ticks): 0xFFFFFF every DTC, else one DTC code. False: no such group."""
    if group == 0xFFFFFF:
        idx = range(len(DTCS))
    elif group in BY_CODE:
        idx = (BY_CODE[group],)
    else:
        return False
    clear_entries(mem.record, idx)
    return True


def status_of(mem, i: int) -> int:
    return mem.entries[i].status & AVAILABILITY_MASK
