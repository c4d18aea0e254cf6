"""WebSocket framing (RFC 6455 §5), the one copy the bench's hub (``hil.hub``: the server
side) and its clients (``hil.transport.bus.fast_remote_client``: python-can-remote's client made
cheaper per frame; the fault campaign's malformed client) share: a frame's header, the
payload's mask, the opening handshake's accept key. Final frames only: neither side sends
fragments."""

from __future__ import annotations

import base64
import hashlib
from typing import Optional

TEXT, BINARY, CLOSE, PING, PONG = 0x1, 0x2, 0x8, 0x9, 0xA
_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"


def accept_key(key: str) -> str:
    """``Sec-WebSocket-Accept`` for a client's ``Sec-WebSocket-Key``."""
    return base64.b64encode(hashlib.sha1(key.encode("ascii") + _GUID).digest()).decode()


def xor(data, mask: bytes) -> bytes:
    """The payload masked (or unmasked) with a client's 4-byte key: one integer XOR."""
    n = len(data)
    if not n:
        return b""
    key = (mask * (n // 4 + 1))[:n]
    return (int.from_bytes(data, "big") ^ int.from_bytes(key, "big")).to_bytes(n, "big")


def frame(opcode: int, payload, mask: Optional[bytes] = None) -> bytes:
    """A final frame: a server's unmasked, a client's masked with ``mask``."""
    n = len(payload)
    bit = 0x80 if mask else 0
    if n <= 125:
        head = bytes((0x80 | opcode, bit | n))
    elif n <= 0xFFFF:
        head = bytes((0x80 | opcode, bit | 126)) + n.to_bytes(2, "big")
    else:
        head = bytes((0x80 | opcode, bit | 127)) + n.to_bytes(8, "big")
    return head + mask + xor(payload, mask) if mask else head + bytes(payload)


def header_size(second_byte: int) -> int:
    """The bytes of a frame's header (the mask key included) from its second byte."""
    n = second_byte & 0x7F
    return 2 + (2 if n == 126 else 8 if n == 127 else 0) + (4 if second_byte & 0x80 else 0)


def header(buf) -> tuple[int, int, Optional[bytes]]:
    """(opcode, payload length, mask key or None) of the frame at the start of ``buf``, which
    holds at least its ``header_size`` bytes; the payload follows them."""
    b2 = buf[1]
    n, pos = b2 & 0x7F, 2
    if n == 126:
        n, pos = int.from_bytes(buf[2:4], "big"), 4
    elif n == 127:
        n, pos = int.from_bytes(buf[2:10], "big"), 10
    return buf[0] & 0x0F, n, bytes(buf[pos:pos + 4]) if b2 & 0x80 else None
