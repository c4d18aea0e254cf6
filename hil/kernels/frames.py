"""CAN frames in compiled code: the same bytes and the same receive checks as ``hil.transport.codec`` and
``firmware.safety`` (which stay the reference: ``tests/test_frames.py`` holds the two
together), over tables laid out once from the DBC (``hil.transport.codec.Codec.frame_tables``).

Tables (structured arrays, one row each):

- ``MSG``: a message: ID, DLC, where its COUNTER and CHECKSUM are (-1: none), the CRC-8
  register after its ID's two bytes (``firmware.safety.checksum_of`` starts there), and the
  rows of ``FIELD`` that a receiver checks against the DBC's declared range (RANGE).
- ``FIELD``: a signal: start bit, mask, sign bit (0: unsigned), its raw range (packing
  saturates there), its declared range as raw integers, scale and offset.
- ``RX``: a receiver's view of one message (``firmware.safety.RxState`` with the spec's
  supervision: COUNTER and CHECKSUM checked or not, timeout, minimum interval, recovery).

A payload is handled as a little-endian word of up to 64 bits (``load``/``store``): numba's
int64 wraps where Python's integers grow, and every field is masked, so both give the same
bits (``NUMBA_DISABLE_JIT=1`` runs this same source).
"""

from __future__ import annotations

import math

import numpy as np

from firmware import safety
from firmware.kernels import INTERPRETED, njit
from firmware.layout import canonical
from firmware.util import round_half_away

MSG = np.dtype([("id", "i8"), ("dlc", "i8"), ("counter_bit", "i8"), ("checksum_byte", "i8"),
                ("id_crc", "i8"), ("range_first", "i8"), ("range_n", "i8")])
FIELD = np.dtype([("start", "i8"), ("mask", "i8"), ("sign", "i8"), ("lo", "i8"), ("hi", "i8"),
                  ("dlo", "i8"), ("dhi", "i8"), ("scale", "f8"), ("offset", "f8")])
RX = np.dtype([("cc", "i8"), ("timeout", "i8"), ("min_interval", "i8"), ("recover", "i8"),
               ("valid", "i8"), ("good_run", "i8"), ("last_counter", "i8"), ("last_rx_tick", "i8"),
               ("faults", "i8")])

CRC_TABLE = np.array(safety._CRC_TABLE, dtype=np.int64)
FAULT_DLC, FAULT_CHECKSUM, FAULT_COUNTER = safety.FAULT_DLC, safety.FAULT_CHECKSUM, \
    safety.FAULT_COUNTER
FAULT_RATE, FAULT_RANGE, FAULT_TIMEOUT = safety.FAULT_RATE, safety.FAULT_RANGE, \
    safety.FAULT_TIMEOUT


def table(dtype: np.dtype, n: int) -> np.ndarray:
    """``n`` zeroed rows of a table (a recarray where the interpreter runs the kernels: its
    rows' fields are attributes, as numba's are)."""
    arr = np.zeros(n, canonical(dtype))
    return arr.view(np.recarray) if INTERPRETED else arr


def supervise(row, spec) -> None:
    """A receiver's row supervised as ``spec`` says (a ``firmware.safety.FrameSpec``: COUNTER
    and CHECKSUM checked where it has them, timeout, minimum interval, recovery)."""
    row["cc"] = spec.counter_bit is not None
    row["timeout"], row["min_interval"] = spec.timeout_ticks, spec.min_interval_ticks
    row["recover"] = spec.recover_frames


def rx_table(n: int) -> np.ndarray:
    """``n`` receivers in ``RxState``'s initial state (no supervision: set the spec's)."""
    rx = table(RX, n)
    rx["cc"] = 1
    rx["recover"] = 1
    rx["last_counter"] = -1
    rx["last_rx_tick"] = -1
    return rx


@njit
def load(buf, dlc):
    """The payload ``buf[:dlc]`` as a little-endian word."""
    w = 0
    for i in range(dlc):
        w |= int(buf[i]) << (8 * i)
    return w


@njit
def store(buf, dlc, w) -> None:
    for i in range(dlc):
        buf[i] = (w >> (8 * i)) & 0xFF


@njit
def put(w, f, v):
    """``w`` with the raw value ``v`` of field ``f`` packed in, saturated at its raw range
    (``hil.transport.codec._pack_word``)."""
    v = int(v)
    if v > f.hi:
        v = int(f.hi)
    elif v < f.lo:
        v = int(f.lo)
    return w | ((v & int(f.mask)) << int(f.start))


@njit
def to_raw(f, value):
    """A physical value as the field's raw integer (``hil.transport.codec._to_raw``: half away from
    zero, saturated at the declared range; NaN: 0 or the nearest end of the range)."""
    if math.isnan(value):
        return min(f.dhi, max(f.dlo, 0))
    if math.isinf(value):
        return f.dhi if value > 0 else f.dlo
    raw = (value - f.offset) / f.scale
    if raw >= f.dhi:
        return f.dhi
    if raw <= f.dlo:
        return f.dlo
    return min(f.dhi, max(f.dlo, round_half_away(raw)))


@njit
def get(w, f):
    """Field ``f``'s raw value in the word ``w`` (sign-extended)."""
    v = (w >> int(f.start)) & int(f.mask)
    sign = int(f.sign)
    if v & sign:
        v -= sign << 1
    return v


@njit
def checksum(m, buf):
    """``firmware.safety.checksum_of``: CRC-8 over the ID's two bytes and the payload without
    the CHECKSUM byte."""
    crc = int(m.id_crc)
    for i in range(m.dlc):
        if i != m.checksum_byte:
            crc = int(CRC_TABLE[crc ^ int(buf[i])])
    return crc ^ 0xFF


@njit
def seal(m, buf, w, counter, with_checksum) -> None:
    """``firmware.safety.seal_word`` into ``buf``: the word with COUNTER written, then the
    CHECKSUM over the result (unless ``with_checksum`` is False: SecOC writes it later)."""
    cb = int(m.counter_bit)
    if cb >= 0:
        w = (w & ~(0xF << cb)) | ((int(counter) & 0xF) << cb)
    if m.checksum_byte >= 0:
        w &= ~(0xFF << (8 * int(m.checksum_byte)))
    store(buf, m.dlc, w)
    if m.checksum_byte >= 0 and with_checksum:
        buf[m.checksum_byte] = checksum(m, buf)


@njit
def counter_of(m, buf):
    return (load(buf, m.dlc) >> int(m.counter_bit)) & 0xF


@njit
def check(m, rx, buf, n, tick):
    """``firmware.safety.check_frame`` (COUNTER and CHECKSUM checked where the receiver's
    ``cc`` says so): True if the frame may be used; updates the receiver."""
    own_cc = rx.cc != 0
    faults = 0
    if n != m.dlc:
        faults |= FAULT_DLC
    else:
        if own_cc and m.checksum_byte >= 0 and int(buf[m.checksum_byte]) != checksum(m, buf):
            faults |= FAULT_CHECKSUM
        if own_cc and m.counter_bit >= 0 and faults == 0:
            c = counter_of(m, buf)
            if rx.last_counter >= 0 and c != ((rx.last_counter + 1) & 0xF):
                faults |= FAULT_COUNTER
            rx.last_counter = c
    if (faults == 0 and rx.min_interval != 0 and rx.last_rx_tick >= 0
            and tick - rx.last_rx_tick < rx.min_interval):
        rx.faults = FAULT_RATE
        return False
    rx.faults = faults
    if faults != 0:
        rx.valid = 0
        rx.good_run = 0
        return False
    rx.last_rx_tick = tick
    rx.good_run += 1
    if rx.good_run >= rx.recover:
        rx.valid = 1
    return True


@njit
def in_range(F, m, w):
    """Every signal the DBC declares narrower than its raw range is inside it."""
    for j in range(m.range_first, m.range_first + m.range_n):
        f = F[j]
        v = get(w, f)
        if v < f.dlo or v > f.dhi:
            return False
    return True


@njit
def receive(F, m, rx, buf, n, tick):
    """``check``, then the range of every ranged signal (``hil.transport.codec`` ``decode``'s order);
    True for a usable frame. A frame out of range invalidates the message (RANGE)."""
    if not check(m, rx, buf, n, tick):
        return False
    if not in_range(F, m, load(buf, m.dlc)):
        rx.faults |= FAULT_RANGE
        rx.valid = 0
        rx.good_run = 0
        return False
    return True


@njit
def timed_out(rx, tick):
    """``not firmware.safety.check_timeout``: True (and the message invalid) when it has not
    arrived in time."""
    if rx.timeout != 0 and (rx.last_rx_tick < 0 or tick - rx.last_rx_tick > rx.timeout):
        if rx.last_rx_tick >= 0 or tick > rx.timeout:
            rx.valid = 0
            rx.good_run = 0
            rx.faults |= FAULT_TIMEOUT
            return True
    return False
