"""Safety as data, panda style: everything that decides what the ECU trusts and when it may
push, in one place.

* ``RX_CHECKS``: the messages the ECU receives, with their period, timeout, COUNTER/CHECKSUM
  and minimum interval; ``TX_MESSAGES``: the only messages it sends (``tests/test_dbc.py``
  holds both to the DBC).
* The fault word (``FAULT_*``, ``fault_names``) and which faults are safety-relevant
  (``SAFETY_RELEVANT``): such a fault opens the bridge in the same tick.
* The final gate (in the tick, ``firmware.ecu._control`` and ``firmware.fx.path.control``):
  active force only in an active mode (or while a crossfade into passive runs) and never
  with a safety-relevant fault; otherwise the bridge is opened (passive damping remains).
* Frame validity, below: CRC-8 CHECKSUM, 4-bit COUNTER, DLC, and receive timeouts with
  hysteresis. Written once, here; the HIL codec reuses it (two copies drift). Pure code: time
  is a tick count.

CHECKSUM: CRC-8 SAE J1850 (polynomial 0x1D, init 0xFF, final XOR 0xFF) over the message ID as
two bytes (little-endian) followed by the payload bytes, the CHECKSUM byte left out (the ID
protects against a frame masquerading as another message). COUNTER: increments by 1 per frame and wraps
at 15; a repeat or a jump is a fault. A message is *valid* only after ``recover_frames``
consecutive good frames (hysteresis) and becomes invalid on any bad frame or when nothing
arrived for ``timeout_ticks``. RATE: a frame arriving less than ``min_interval_ticks`` after the
last accepted one (a node flooding the bus) is not used and flagged, but does not invalidate
the message (its content may be fine). RANGE: a decoded value outside the DBC's declared
[minimum, maximum] makes the frame invalid (``hil.transport.codec`` checks it, after DLC and CHECKSUM).
"""

from __future__ import annotations

from dataclasses import dataclass

from firmware import adc

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


# ---------------------------------------------------------------- the fault word
# bits 0-4: the ADC channels (firmware.adc.FAULT_BIT, in adc.CHANNELS order)
FAULT_AUTH = 1 << 5               # a secured message failed its SecOC check (ignored)
FAULT_PLAUSIBILITY = 1 << 6       # model-based: a sensor or the actuator disagrees with the
#                                   model (firmware.diag.fdi; the DTC names which)
FAULT_RATE = 1 << 7               # a message (or driver request) arrived faster than allowed
FAULT_NONFINITE_ESTIMATE = 1 << 8  # the estimator diverged (reset, fail-safe this tick)
FAULT_INVALID_REQUEST = 1 << 9    # driver request with an invalid mode (informational)
# 10-15: frame validity of the receive path
FAULT_DLC = 1 << 10
FAULT_CHECKSUM = 1 << 11
FAULT_COUNTER = 1 << 12
FAULT_TIMEOUT = 1 << 13
FAULT_UNKNOWN_ID = 1 << 14
FAULT_RANGE = 1 << 15             # a signal outside its declared range
FAULT_SUPPLY = 1 << 16            # the supply voltage outside its operating range (fail-safe;
#                                   on the bus: ECU_STATUS.FAULT_SUPPLY)
FAULT_SAMPLE = 1 << 17            # a tick without a sensor sample, and the ADC's recovery after
#                                   it (fail-safe; no DTC of its own: the frame's names the cause)

FAULT_NAMES = {**{bit: name for name, bit in adc.FAULT_BIT.items()},
               FAULT_AUTH: "auth", FAULT_PLAUSIBILITY: "plausibility", FAULT_RATE: "rate",
               FAULT_NONFINITE_ESTIMATE: "estimator_reset",
               FAULT_INVALID_REQUEST: "invalid_request", FAULT_DLC: "dlc",
               FAULT_CHECKSUM: "checksum", FAULT_COUNTER: "counter",
               FAULT_TIMEOUT: "timeout", FAULT_UNKNOWN_ID: "unknown_id",
               FAULT_RANGE: "range", FAULT_SUPPLY: "supply", FAULT_SAMPLE: "sample"}

# faults that make active control unsafe: every measured channel, a diverged estimator, a
# sensor or actuator the model-based tests found implausible, a supply out of its range
SAFETY_RELEVANT = (adc.FAULT_BIT["body_accel"] | adc.FAULT_BIT["wheel_accel"]
                   | adc.FAULT_BIT["susp_defl"] | adc.FAULT_BIT["motor_current"]
                   | adc.FAULT_BIT["speed"] | FAULT_NONFINITE_ESTIMATE | FAULT_PLAUSIBILITY
                   | FAULT_SUPPLY | FAULT_SAMPLE)


def fault_names(word: int) -> list[str]:
    """The names of the bits set in a fault word (lowest bit first)."""
    return [name for bit, name in sorted(FAULT_NAMES.items()) if word & bit]


# ---------------------------------------------------------------- receive and transmit


@dataclass(frozen=True)
class RxCheck:
    """A message the ECU receives: how it is supervised."""

    message: str
    period_ms: int                 # the DBC's GenMsgCycleTime
    timeout_periods: int           # invalid after this many periods without a frame (0: none;
    #                                PLANT_SENSORS drives the tick: a tick without it is the fault)
    counter_checksum: bool         # COUNTER and CHECKSUM are checked
    min_interval_periods: float    # a copy sooner than this (in periods) is not used: RATE
    recover_frames: int = 1        # consecutive good frames before the message is valid again

    def ticks(self, dt_s: float) -> tuple[int, int, int]:
        """(period, timeout, minimum interval) in ticks of ``dt_s``."""
        period = max(1, int(round(self.period_ms * 1e-3 / dt_s)))
        min_interval = max(1, int(period * self.min_interval_periods)) \
            if self.min_interval_periods else 0
        return period, self.timeout_periods * period, min_interval


RX_CHECKS = (
    RxCheck("PLANT_SENSORS", 1, 0, True, 0.0),
    RxCheck("VEHICLE_SPEED", 10, 3, True, 0.5),
    RxCheck("PLANT_SUPPLY", 10, 3, True, 0.5),
    RxCheck("DRIVER_REQUEST", 100, 0, True, 0.0),
)
TX_MESSAGES = ("ACTUATOR_CMD", "ECU_STATUS", "ECU_ESTIMATES", "MODE_RECOMMEND",
               "DIAG_RESPONSE", "XCP_RES")


# ---------------------------------------------------------------- frame validity


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
