"""Secured messages: AUTOSAR SecOC profile 1 on the two messages that command something,
``ACTUATOR_CMD`` (ECU -> plant: the bridge) and ``DRIVER_REQUEST`` (app -> ECU: the mode).

Profile 1 ("24Bit-CMAC-8Bit-FV"): the authenticator is AES-128 CMAC (NIST SP 800-38B, from
the ``cryptography`` package) truncated to its first 24 bits, over

    data ID (the CAN ID, 2 bytes big-endian) || authentic PDU || freshness value (8 bytes BE)

where the authentic PDU is the payload without its ``FRESHNESS``, ``MAC`` and ``CHECKSUM``
bytes, and the freshness value is a 64-bit counter per message and direction, one up per
frame sent; its low 8 bits travel in ``FRESHNESS``. The CHECKSUM (CRC-8, ``firmware.safety``)
is computed last, over the MAC too. A receiver checks the MAC before COUNTER and ranges
(``Receiver.forged``): a frame that fails it is an attacker's if its DLC and CHECKSUM hold, a
transmission error if not; so a forged or replayed frame never touches the receiver's
COUNTER state.

Freshness on receive: the full value is rebuilt from the 8 bits as the smallest value above
the last accepted one with those low bits; a MAC that fails there is tried in the next
``RESYNC_WINDOWS - 1`` windows of 256 (so up to 1,023 lost frames in a row resynchronise by
themselves). A replayed frame rebuilds to a value it was not signed with, and fails. A frame
accepted moves the last value on; nothing else does.

Keys: 16 random bytes as 32 hex digits in a key file, mode 0600 (a key file readable by group
or others is refused). ``hil run`` writes a new one per run into its ``--out`` directory;
``--key-file FILE`` shares one (between ``hil sim`` and ``hil run``, for byte-equal logs).
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

from calib.errors import ConfigError
from firmware import safety

SECURED = ("ACTUATOR_CMD", "DRIVER_REQUEST")
KEY_BYTES = 16
MAC_BITS = 24
FV_BITS = 8
RESYNC_WINDOWS = 4
KEY_FILE_NAME = "secoc.key"


def new_key() -> bytes:
    return os.urandom(KEY_BYTES)


def write_key(path: str | Path, key: Optional[bytes] = None) -> bytes:
    """Write a new key file (mode 0600, never over an existing file); returns the key."""
    key = key or new_key()
    path = Path(path)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    return key


def load_key(path: str | Path, where: str = "") -> bytes:
    """The key of a key file; a clear ConfigError for a missing, unreadable, shared (mode) or
    malformed file. ``where``: where a missing file comes from (default: hil keygen makes
    one)."""
    path = Path(path)
    try:
        st = path.stat()
        text = path.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such key file ("
                          + (where or f"make one with python -m hil keygen {path}")
                          + ")") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the key file: {exc}") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(f"{path}: key file is accessible to others (mode "
                          f"{stat.S_IMODE(st.st_mode):04o}); chmod 600 {path}")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise ConfigError(f"{path}: a key file holds {2 * KEY_BYTES} hex digits (AES-128)")
    return key


@dataclass(frozen=True)
class Layout:
    """Where a secured message keeps its freshness and MAC (whole bytes, from the DBC)."""
    name: str
    frame_id: int
    spec: safety.FrameSpec
    fv_byte: int
    mac_byte: int

    @property
    def trailer(self) -> frozenset:
        out = {self.fv_byte, *range(self.mac_byte, self.mac_byte + MAC_BITS // 8)}
        if self.spec.checksum_byte is not None:
            out.add(self.spec.checksum_byte)
        return frozenset(out)


def layout(codec, name: str) -> Layout:
    """The layout of ``name`` in the codec's DBC; ValueError if it has no byte-aligned 8-bit
    FRESHNESS and 24-bit MAC."""
    m = codec.message(name)
    sig = {s.name: s for s in m.signals}
    fv, mac = sig.get("FRESHNESS"), sig.get("MAC")
    if fv is None or mac is None or fv.length != FV_BITS or mac.length != MAC_BITS \
            or fv.start % 8 or mac.start % 8:
        raise ValueError(f"{name}: a secured message needs byte-aligned FRESHNESS "
                         f"({FV_BITS} bits) and MAC ({MAC_BITS} bits) signals in the DBC")
    return Layout(name, m.frame_id, codec.specs[m.frame_id], fv.start // 8, mac.start // 8)


class _Mac:
    def __init__(self, key: bytes, lay: Layout):
        self.key = key
        self.base = CMAC(algorithms.AES(key))
        self.lay = lay
        self.head = lay.frame_id.to_bytes(2, "big")
        keep = [i for i in range(lay.spec.dlc) if i not in lay.trailer]
        # the authentic PDU's bytes as slices (one, for both secured messages)
        self.runs = [(a, b + 1) for a, b in _runs(keep)]

    def of(self, data: bytes, fv: int) -> bytes:
        c = self.base.copy()
        c.update(self.head)
        for a, b in self.runs:
            c.update(data[a:b])
        c.update(fv.to_bytes(8, "big"))
        return c.finalize()[:MAC_BITS // 8]

    def __deepcopy__(self, memo):         # (the CMAC context itself does not copy)
        return _Mac(self.key, self.lay)


def _runs(idx: list[int]) -> list[tuple[int, int]]:
    """Consecutive runs of sorted indices as (first, last) pairs."""
    out: list[list[int]] = []
    for i in idx:
        if out and i == out[-1][1] + 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return [(a, b) for a, b in out]


class Sender:
    """Signs the frames of one message: freshness one up per frame."""

    def __init__(self, key: bytes, lay: Layout):
        self.mac = _Mac(key, lay)
        self.lay = lay
        self.fv = 0

    def protect(self, data: bytes) -> bytes:
        self.fv += 1
        lay = self.lay
        out = bytearray(data)
        out[lay.fv_byte] = self.fv & 0xFF
        out[lay.mac_byte:lay.mac_byte + MAC_BITS // 8] = self.mac.of(out, self.fv)
        cb = lay.spec.checksum_byte
        if cb is not None:
            out[cb] = safety.checksum_of(lay.spec, out)
        return bytes(out)


class Receiver:
    """Verifies the frames of one message; counts what it rejects."""

    def __init__(self, key: bytes, lay: Layout):
        self.mac = _Mac(key, lay)
        self.lay = lay
        self.latest = 0                 # the freshness value last accepted
        self.rejected = 0

    def verify(self, data: bytes) -> bool:
        """True for an authentic, fresh frame (and the freshness moves on); False for a bad
        MAC, a replay or a stale frame (counted). A frame that fails its CHECKSUM fails here
        too: callers that must tell the two apart check the CHECKSUM of a failed one."""
        lay = self.lay
        if len(data) != lay.spec.dlc:
            self.rejected += 1
            return False
        low = data[lay.fv_byte]
        tag = bytes(data[lay.mac_byte:lay.mac_byte + MAC_BITS // 8])
        fv = (self.latest & ~0xFF) | low
        if fv <= self.latest:
            fv += 0x100
        for _ in range(RESYNC_WINDOWS):
            if self.mac.of(data, fv) == tag:
                self.latest = fv
                return True
            fv += 0x100
        self.rejected += 1
        return False

    def forged(self, data: bytes) -> bool:
        """True for a frame whose DLC and CHECKSUM hold but whose MAC or freshness fails (an
        attacker, not a transmission error); an authentic one moves the freshness on. MAC
        first: an authentic frame then costs no CRC here (the unpacker checks it)."""
        if self.verify(data):
            return False
        spec = self.lay.spec
        return len(data) == spec.dlc and (spec.checksum_byte is None or data[
            spec.checksum_byte] == safety.checksum_of(spec, data))


def sender(codec, key: Optional[bytes], name: str) -> Optional[Sender]:
    """The signer of ``name`` for a node with ``key`` (None without a key: the unsecured
    path, for tests of the receive path only)."""
    return None if key is None else Sender(key, layout(codec, name))


def receiver(codec, key: Optional[bytes], name: str) -> Optional[Receiver]:
    """The verifier of ``name`` for a node with ``key`` (None without a key)."""
    return None if key is None else Receiver(key, layout(codec, name))
