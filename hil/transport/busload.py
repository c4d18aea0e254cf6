"""A CAN bus's load: the bits of a classic data frame and the DBC's cyclic traffic
(``tools.busload`` reports it; the XCP slave's DAQ budget counts against it)."""

from __future__ import annotations

from hil.transport.codec import Codec


def frame_bits(dlc: int, worst_case: bool = True) -> int:
    """A classic CAN data frame with an 11-bit ID: 47 + 8 n bits, plus worst-case bit
    stuffing floor((34 + 8 n - 1) / 4) over the stuffed part (SOF to CRC)."""
    bits = 47 + 8 * dlc
    if worst_case:
        bits += (34 + 8 * dlc - 1) // 4
    return bits


def cyclic(codec: Codec | None = None) -> list[dict]:
    """Each cyclic message of the DBC: name, ID, DLC, cycle, bits per frame and per second."""
    codec = codec or Codec()
    rows = []
    for m in codec.db.messages:
        if not m.cycle_time:
            continue
        bits = frame_bits(m.length)
        rows.append({"message": m.name, "id": m.frame_id, "dlc": m.length,
                     "cycle_ms": m.cycle_time, "bits_per_frame": bits,
                     "bits_per_s": bits * 1000.0 / m.cycle_time})
    return rows


def dbc_bits_per_s(codec: Codec | None = None) -> float:
    return sum(r["bits_per_s"] for r in cyclic(codec))
