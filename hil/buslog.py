"""The bus log: every frame in candump ``-L`` format (python-can's ``CanutilsLogWriter``),
readable by ``python -m can.player``, ``python -m cantools decode`` and can-utils.

In lockstep pacing the timestamps are simulated time (``hil.nodes.LockstepClock``), so a run
and its in-process twin (``hil sim``) write the same lines; in realtime pacing they are the
wall-clock receive times.
"""

from __future__ import annotations

from pathlib import Path

import can

LOG_CHANNEL = "vcan0"


class BusLogFile:
    """Append frames to a candump log; counts frames per ID; flushes on demand and on close."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = can.io.CanutilsLogWriter(str(self.path), channel=LOG_CHANNEL)
        self.count = 0
        self.by_id: dict[int, int] = {}

    def write(self, fid: int, data: bytes, timestamp: float) -> None:
        self._writer.on_message_received(can.Message(
            timestamp=timestamp, arbitration_id=fid, data=data, is_extended_id=False,
            is_rx=True, channel=LOG_CHANNEL))
        self.count += 1
        self.by_id[fid] = self.by_id.get(fid, 0) + 1

    def flush(self) -> None:
        self._writer.file.flush()

    def close(self) -> None:
        self._writer.stop()


def read_log(path: Path) -> list[tuple[float, int, bytes]]:
    """(timestamp, id, payload) of every frame of a candump log, in file order."""
    out = []
    for msg in can.io.CanutilsLogReader(str(path)):
        out.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))
    return out


def compare(reference: Path, other: Path) -> dict:
    """Two candump logs frame by frame, timestamps aside: counts, frames per ID, and the first
    frame (index, both sides) where ID or payload or order differ. ``equal`` when the frame
    lists are the same."""
    a = [(fid, data) for _, fid, data in read_log(reference)]
    b = [(fid, data) for _, fid, data in read_log(other)]
    first = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y),
                 None if len(a) == len(b) else min(len(a), len(b)))
    ids = sorted({fid for fid, _ in a} | {fid for fid, _ in b})
    count = {f: [0, 0] for f in ids}
    for side, frames in enumerate((a, b)):
        for fid, _ in frames:
            count[fid][side] += 1
    out = {"reference": str(reference), "other": str(other), "frames": [len(a), len(b)],
           "ids": {f"0x{f:03X}": count[f] for f in ids}, "equal": first is None,
           "first_difference": None}
    if first is not None:
        def show(frames, i):
            if i >= len(frames):
                return "(end)"
            return f"{frames[i][0]:03X}#{frames[i][1].hex().upper()}"
        out["first_difference"] = {"index": first, "reference": show(a, first),
                                   "other": show(b, first)}
    return out


def render_compare(c: dict) -> str:
    lines = [f"{c['reference']}: {c['frames'][0]} frames; {c['other']}: {c['frames'][1]} frames"]
    for fid, (x, y) in c["ids"].items():
        lines.append(f"  {fid}  {x:8d}  {y:8d}" + ("" if x == y else "   differs"))
    if c["equal"]:
        lines.append("the same frames (IDs and payloads) in the same order")
    else:
        d = c["first_difference"]
        lines.append(f"first difference at frame {d['index']}: {d['reference']} against "
                     f"{d['other']}")
    return "\n".join(lines)
