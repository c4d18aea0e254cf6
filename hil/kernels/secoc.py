"""SecOC profile 1 in compiled code: ``hil.transport.secoc``'s ``Sender.protect`` and
``Receiver.forged`` (the reference, ``tests/test_frames.py``) over a table row per secured
message and direction, with libcrypto's AES-CMAC (``hil.kernels.cmac``).

``SEC``: the message's ID and DLC, where FRESHNESS, MAC and CHECKSUM are, and the freshness
state: a sender's last value sent or a receiver's last value accepted, with the frames it
rejected.
"""

from __future__ import annotations

import numpy as np

from firmware.kernels import njit
from hil.kernels.cmac import cmac
from hil.kernels.frames import checksum

SEC = np.dtype([("fv_byte", "i8"), ("mac_byte", "i8"), ("fv", "i8"), ("rejected", "i8")])
MAC_BYTES = 3
RESYNC_WINDOWS = 4


@njit
def mac_of(m, s, buf, fv, ctx, msg, tag16, length):
    """The CMAC of data ID (2 bytes, big-endian) || the authentic PDU (the payload without
    FRESHNESS, MAC and CHECKSUM) || the freshness value (8 bytes, big-endian), in ``tag16``;
    False where libcrypto fails."""
    fid = int(m.id)
    msg[0] = (fid >> 8) & 0xFF
    msg[1] = fid & 0xFF
    n = 2
    for i in range(m.dlc):
        if i == s.fv_byte or (s.mac_byte <= i < s.mac_byte + MAC_BYTES) or i == m.checksum_byte:
            continue
        msg[n] = buf[i]
        n += 1
    for j in range(8):
        msg[n] = (fv >> (8 * (7 - j))) & 0xFF
        n += 1
    return cmac(ctx, msg, n, tag16, length)


@njit
def protect(m, s, buf, ctx, msg, tag16, length) -> None:
    """``Sender.protect``: freshness one up, its low byte, the truncated MAC, the CHECKSUM."""
    s.fv += 1
    fv = int(s.fv)
    buf[s.fv_byte] = fv & 0xFF
    mac_of(m, s, buf, fv, ctx, msg, tag16, length)
    for j in range(MAC_BYTES):
        buf[s.mac_byte + j] = tag16[j]
    if m.checksum_byte >= 0:
        buf[m.checksum_byte] = checksum(m, buf)


@njit
def verify(m, s, buf, n, ctx, msg, tag16, length):
    """``Receiver.verify``: True for an authentic, fresh frame (the freshness moves on)."""
    if n != m.dlc:
        s.rejected += 1
        return False
    latest = int(s.fv)
    fv = (latest & ~0xFF) | int(buf[s.fv_byte])
    if fv <= latest:
        fv += 0x100
    for _ in range(RESYNC_WINDOWS):
        if mac_of(m, s, buf, fv, ctx, msg, tag16, length):
            same = True
            for j in range(MAC_BYTES):
                if tag16[j] != buf[s.mac_byte + j]:
                    same = False
            if same:
                s.fv = fv
                return True
        fv += 0x100
    s.rejected += 1
    return False


@njit
def forged(m, s, buf, n, ctx, msg, tag16, length):
    """``Receiver.forged``: True for a frame whose DLC and CHECKSUM hold but whose MAC or
    freshness fails (an attacker); an authentic one moves the freshness on."""
    if verify(m, s, buf, n, ctx, msg, tag16, length):
        return False
    return n == m.dlc and (m.checksum_byte < 0 or int(buf[m.checksum_byte]) == checksum(m, buf))
