"""Frame validity: CRC-8 CHECKSUM, 4-bit COUNTER, DLC, and receive timeouts with hysteresis.

Written once, here; the HIL codec reuses it (two copies drift). Pure code: time is a tick count.

CHECKSUM: CRC-8 SAE J1850 (polynomial 0x1D, init 0xFF, final XOR 0xFF) over the message ID as
two bytes (little-endian) followed by the payload bytes, the CHECKSUM byte left out (the ID
protects against a frame masquerading as another message). COUNTER: increments by 1 per frame and wraps
at 15; a repeat or a jump is a fault. A message is *valid* only after ``recover_frames``
consecutive good frames (hysteresis) and becomes invalid on any bad frame or when nothing
arrived for ``timeout_ticks``. RATE: a frame arriving less than ``min_interval_ticks`` after the
last accepted one (a node flooding the bus) is not used and flagged, but does not invalidate
the message (its content may be fine). RANGE: a decoded value outside the DBC's declared
[minimum, maximum] makes the frame invalid (``hil.codec`` checks it, after DLC and CHECKSUM).
"""

from __future__ import annotations

from dataclasses import dataclass

CRC8_POLY = 0x1D
CRC8_INIT = 0xFF
CRC8_XOROUT = 0xFF


def _table() -> tuple[int, ...]:
    out = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        out.append(crc)
    return tuple(out)


_CRC_TABLE = _table()


def crc8(data: bytes | bytearray) -> int:
    crc = CRC8_INIT
    for b in data:
        crc = _CRC_TABLE[crc ^ b]
    return crc ^ CRC8_XOROUT


# fault bits of frame validity (the ECU's fault word; bits 0-4 are the ADC channels, 8-9 the
# estimator and the driver request)
FAULT_RATE = 1 << 7               # a message (or driver request) arrived faster than allowed
FAULT_DLC = 1 << 10
FAULT_CHECKSUM = 1 << 11
FAULT_COUNTER = 1 << 12
FAULT_TIMEOUT = 1 << 13
FAULT_UNKNOWN_ID = 1 << 14
FAULT_RANGE = 1 << 15             # a signal outside its declared range


@dataclass(frozen=True)
class FrameSpec:
    """What the receiver knows of one message."""

    msg_id: int
    dlc: int
    counter_bit: int | None       # little-endian start bit of the 4-bit COUNTER
    checksum_byte: int | None     # byte index of the 8-bit CHECKSUM
    timeout_ticks: int = 0        # 0: no timeout supervision
    recover_frames: int = 1
    min_interval_ticks: int = 0   # 0: no rate supervision


_ID_CRC: dict[int, int] = {}    # the CRC register after a message ID's two bytes (a cache)


def checksum_of(spec: FrameSpec, data: bytes | bytearray) -> int:
    """crc8(ID as two bytes, little-endian + the payload without the CHECKSUM byte)."""
    crc = _ID_CRC.get(spec.msg_id)
    if crc is None:
        crc = CRC8_INIT
        for b in (spec.msg_id & 0xFFFF).to_bytes(2, "little"):
            crc = _CRC_TABLE[crc ^ b]
        _ID_CRC[spec.msg_id] = crc
    cb = spec.checksum_byte
    table = _CRC_TABLE
    for b in (data if cb is None else data[:cb] + data[cb + 1:]):
        crc = table[crc ^ b]
    return crc ^ CRC8_XOROUT


def counter_of(spec: FrameSpec, data: bytes | bytearray) -> int:
    return (int.from_bytes(bytes(data), "little") >> spec.counter_bit) & 0xF


def seal(spec: FrameSpec, data: bytes | bytearray, counter: int) -> bytes:
    """Write COUNTER and CHECKSUM into a payload (the sender's side)."""
    return seal_word(spec, int.from_bytes(bytes(data), "little"), len(data), counter)


def seal_word(spec: FrameSpec, word: int, length: int, counter: int) -> bytes:
    """``seal`` for a payload given as a little-endian integer of ``length`` bytes."""
    if spec.counter_bit is not None:
        word = (word & ~(0xF << spec.counter_bit)) | ((counter & 0xF) << spec.counter_bit)
    cb = spec.checksum_byte
    if cb is not None:
        word &= ~(0xFF << (8 * cb))
        word |= checksum_of(spec, word.to_bytes(length, "little")) << (8 * cb)
    return word.to_bytes(length, "little")


@dataclass
class RxState:
    valid: bool = False
    good_run: int = 0
    last_counter: int = -1
    last_rx_tick: int = -1
    faults: int = 0               # faults seen on the last frame / check


def check_frame(spec: FrameSpec, st: RxState, data: bytes | bytearray, tick: int) -> bool:
    """Check one received frame; updates validity. Returns True if the frame may be used."""
    faults = 0
    if len(data) != spec.dlc:
        faults |= FAULT_DLC
    else:
        if spec.checksum_byte is not None and data[spec.checksum_byte] != checksum_of(spec, data):
            faults |= FAULT_CHECKSUM
        if spec.counter_bit is not None and not faults:
            c = counter_of(spec, data)
            if st.last_counter >= 0 and c != (st.last_counter + 1) & 0xF:
                faults |= FAULT_COUNTER
            st.last_counter = c
    if (not faults and spec.min_interval_ticks and st.last_rx_tick >= 0
            and tick - st.last_rx_tick < spec.min_interval_ticks):
        st.faults = FAULT_RATE    # too soon: not used, but the message stays valid
        return False
    st.faults = faults
    if faults:
        st.valid, st.good_run = False, 0
        return False
    st.last_rx_tick = tick
    st.good_run += 1
    if st.good_run >= spec.recover_frames:
        st.valid = True
    return True


def invalidate(st: RxState, fault: int) -> None:
    """A frame that passed the checks above but whose content is unusable (e.g. RANGE)."""
    st.faults |= fault
    st.valid, st.good_run = False, 0


def check_timeout(spec: FrameSpec, st: RxState, tick: int) -> bool:
    """Call every tick. False (and invalid) when the message has not arrived in time."""
    if spec.timeout_ticks and (st.last_rx_tick < 0 or tick - st.last_rx_tick > spec.timeout_ticks):
        if st.last_rx_tick >= 0 or tick > spec.timeout_ticks:
            st.valid, st.good_run = False, 0
            st.faults |= FAULT_TIMEOUT
            return False
    return True
