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
