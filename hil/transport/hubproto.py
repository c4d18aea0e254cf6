"""python-can-remote's messages as the hub checks them: a CAN frame in its binary or JSON
form, validated before use (ID range, DLC, data, flags: ``BadMessage`` otherwise), and a
client's acceptance filters."""

from __future__ import annotations

import json
import struct
from typing import Optional

from hil.transport import wsframe as ws

MAX_DATA = {False: 8, True: 64}     # data bytes of a classic / an FD frame
FD_LENGTHS = frozenset((*range(9), 12, 16, 20, 24, 32, 48, 64))
BIN_MSG = struct.Struct(">dIBB")   # can_remote: timestamp, arbitration ID, DLC, flags
BIN_TYPE = 1
IS_EXTENDED_ID, IS_REMOTE_FRAME, IS_ERROR_FRAME, IS_FD, IS_BRS, IS_ESI = (
    0x1, 0x2, 0x4, 0x8, 0x10, 0x20)


class Frame:
    """One CAN frame inside the hub (can_remote's binary layout without the timestamp)."""

    __slots__ = ("arb_id", "dlc", "flags", "data")

    def __init__(self, arb_id: int, dlc: int, flags: int, data: bytes):
        self.arb_id, self.dlc, self.flags, self.data = arb_id, dlc, flags, data

    def binary(self, timestamp: float) -> bytes:
        return ws.frame(ws.BINARY, bytes((BIN_TYPE,))
                        + BIN_MSG.pack(timestamp, self.arb_id, self.dlc, self.flags)
                        + self.data)

    def json(self, timestamp: float) -> bytes:
        f = self.flags
        payload = {"timestamp": timestamp, "arbitration_id": self.arb_id,
                   "is_extended_id": bool(f & IS_EXTENDED_ID),
                   "is_remote_frame": bool(f & IS_REMOTE_FRAME),
                   "is_error_frame": bool(f & IS_ERROR_FRAME), "dlc": self.dlc,
                   "data": list(self.data)}
        if f & IS_FD:
            payload.update(is_fd=True, bitrate_switch=bool(f & IS_BRS),
                           error_state_indicator=bool(f & IS_ESI))
        return ws.frame(ws.TEXT, json.dumps({"type": "message", "payload": payload}).encode())


class BadMessage(ValueError):
    """A client message the hub will not relay (its client is disconnected)."""


_JSON_FLAGS = (("is_extended_id", IS_EXTENDED_ID), ("is_remote_frame", IS_REMOTE_FRAME),
               ("is_error_frame", IS_ERROR_FRAME), ("is_fd", IS_FD),
               ("bitrate_switch", IS_BRS), ("error_state_indicator", IS_ESI))


def checked_frame(arb_id, dlc, flags: int, data: bytes) -> Frame:
    """A frame whose fields a CAN (FD) controller could carry, else BadMessage."""
    extended, fd = bool(flags & IS_EXTENDED_ID), bool(flags & IS_FD)
    top = 0x1FFFFFFF if extended else 0x7FF
    if type(arb_id) is not int or not 0 <= arb_id <= top:
        raise BadMessage(f"arbitration_id {arb_id!r} is not a {'29' if extended else '11'}-bit ID")
    if len(data) > MAX_DATA[fd]:
        raise BadMessage(f"{len(data)} data bytes (at most {MAX_DATA[fd]})")
    if type(dlc) is not int or not 0 <= dlc <= MAX_DATA[fd] or (fd and dlc not in FD_LENGTHS):
        raise BadMessage(f"dlc {dlc!r} is not a CAN{' FD' if fd else ''} length")
    if not flags & IS_REMOTE_FRAME and dlc != len(data):
        raise BadMessage(f"dlc {dlc} but {len(data)} data bytes")
    return Frame(arb_id, dlc, flags, data)


def frame_from_json(p) -> Frame:
    """A ``message`` event's payload as a frame, validated (BadMessage)."""
    if not isinstance(p, dict):
        raise BadMessage("a message payload must be an object")
    flags = 0
    for key, bit in _JSON_FLAGS:
        v = p.get(key, key == "is_extended_id")
        if not isinstance(v, bool):
            raise BadMessage(f"{key} must be true or false, got {v!r}")
        flags |= bit if v else 0
    raw = p.get("data", [])
    if raw is None:
        raw = []
    if not isinstance(raw, list) or len(raw) > MAX_DATA[True]:
        raise BadMessage("data must be a list of at most 64 bytes")
    if not all(type(b) is int and 0 <= b <= 255 for b in raw):
        raise BadMessage("data must hold integers 0..255")
    data = bytes(raw)
    if "arbitration_id" not in p:
        raise BadMessage("a message needs an arbitration_id")
    return checked_frame(p["arbitration_id"], p.get("dlc", len(data)), flags, data)


def parse_filters(raw) -> Optional[list[tuple[int, int, Optional[bool]]]]:
    if not raw:
        return None
    out = []
    for flt in raw:
        ext = flt.get("extended")
        out.append((int(flt["can_id"]), int(flt["can_mask"]), None if ext is None else bool(ext)))
    return out
