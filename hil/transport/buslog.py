"""The bus log: every frame in candump ``-L`` format (python-can's ``CanutilsLogWriter``),
readable by ``python -m can.player``, ``python -m cantools decode`` and can-utils, and on
request the same frames as Vector ASC and BLF, PEAK TRC (python-can's writers) and ASAM MDF 4
(asammdf), converted from it when the run ends.

Each line: ``(time) CHANNEL ID#DATA DIR``.
* time: the run's start time (``--start-time``, default now) plus, in lockstep pacing, the
  simulated time (``hil.nodes.LockstepClock``: a run and its in-process twin, ``hil sim``,
  write the same lines), in realtime pacing the receive time since the start (monotonic).
* CHANNEL: the bus the frames were on: ``vcan0`` (SocketCAN: the interface), ``hub0`` (the
  loopback hub), ``sil0`` (``hil sim``: the nodes in one process).
* DIR: seen from the device under test, the ECU: ``T`` for the frames it sends (their DBC
  sender is ECU), ``R`` for every other.
"""

from __future__ import annotations

import datetime as dt
import functools
from pathlib import Path
from typing import Iterable, Optional

import can
import numpy as np

HUB_CHANNEL = "hub0"
SIL_CHANNEL = "sil0"
LOG_FORMATS = ("log", "asc", "blf", "trc", "mf4")
DUT = "ECU"


@functools.lru_cache(maxsize=1)
def dut_tx_ids() -> frozenset[int]:
    """The IDs of the frames the device under test sends (the DBC's senders)."""
    import cantools

    from hil.transport.codec import DBC_PATH

    db = cantools.database.load_file(str(DBC_PATH), strict=False)
    return frozenset(m.frame_id for m in db.messages if DUT in m.senders)


def parse_start_time(text: Optional[str]) -> int:
    """``--start-time``: ISO 8601 (a time zone, or UTC) or Unix seconds; None: now. In whole
    microseconds since the Unix epoch. ValueError with a clear message on anything else."""
    if text is None:
        return int(dt.datetime.now(dt.timezone.utc).timestamp() * 1_000_000)
    try:
        seconds = float(text)
    except ValueError:
        try:
            when = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(f"--start-time {text!r}: not an ISO 8601 time "
                             "(2026-12-02T09:00:00Z) nor Unix seconds") from None
        if when.tzinfo is None:
            when = when.replace(tzinfo=dt.timezone.utc)
        seconds = when.timestamp()
    if not 0 <= seconds < 2 ** 32:     # (BLF and ASC dates; and NaN)
        raise ValueError(f"--start-time {text!r}: outside 1970..2106")
    return round(seconds * 1_000_000)


def parse_formats(values: Optional[Iterable[str]]) -> tuple[str, ...]:
    """``--log-format`` (repeated or comma-separated): the formats, ``log`` always first."""
    out = ["log"]
    for v in values or ():
        for f in v.split(","):
            f = f.strip().lower().lstrip(".")
            if f not in LOG_FORMATS:
                raise ValueError(f"--log-format {f!r}: one of {', '.join(LOG_FORMATS)}")
            if f not in out:
                out.append(f)
    return tuple(out)


class BusLogFile:
    """Append frames to a candump log; counts frames per ID; flushes on demand and on close.
    ``write`` takes the time since the run's start; ``start_us`` is that start (Unix time in
    microseconds)."""

    def __init__(self, path: Path, channel: str, start_us: int,
                 tx_ids: Optional[frozenset[int]] = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.channel, self.start_us = channel, int(start_us)
        self.tx_ids = dut_tx_ids() if tx_ids is None else tx_ids
        self._writer = can.io.CanutilsLogWriter(str(self.path), channel=channel)
        self.count = 0
        self.by_id: dict[int, int] = {}

    def write(self, fid: int, data: bytes, t_s: float) -> None:
        self._writer.on_message_received(can.Message(
            timestamp=(self.start_us + round(t_s * 1e6)) / 1e6, arbitration_id=fid, data=data,
            is_extended_id=False, is_rx=fid not in self.tx_ids, channel=self.channel))
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


def same_channel(data: bytes, channel: str) -> bytes:
    """A candump log's bytes with every line's channel replaced by ``channel`` (to compare
    the logs of one run on different buses byte for byte)."""
    out = []
    for line in data.split(b"\n"):
        if line.startswith(b"("):
            stamp, _, rest = line.split(b" ", 2)
            line = b" ".join((stamp, channel.encode(), rest))
        out.append(line)
    return b"\n".join(out)


class _AscWriter(can.io.ASCWriter):
    """python-can's ASC writer, dated by the run's start in UTC (its own header takes the
    wall clock of the conversion and the trigger block the local time zone: neither is
    reproducible)."""

    def __init__(self, file, start_us: int, **kwargs):
        self._start = dt.datetime.fromtimestamp(start_us / 1e6, dt.timezone.utc)
        super().__init__(file, **kwargs)

    def _format_header_datetime(self, _when: dt.datetime) -> str:
        return super()._format_header_datetime(self._start)


class _TrcWriter(can.io.TRCWriter):
    """python-can's TRC writer, naming the file it writes as ``name`` in its header (its own
    header has the absolute path of the file it was opened on: the conversion's temporary)."""

    def __init__(self, file, name: str, **kwargs):
        super().__init__(file, **kwargs)
        self.filepath = name


def copies_of(log_path: Path) -> list[Path]:
    """Every copy ``convert`` may write beside the candump log (``bus.asc``, ...)."""
    return [Path(log_path).with_suffix("." + fmt) for fmt in LOG_FORMATS if fmt != "log"]


def convert(log_path: Path, formats: Iterable[str], start_us: int) -> list[Path]:
    """Write the candump log's frames in each other format beside it (``bus.asc``, ...);
    returns the paths written. The candump log is the record: a format that cannot be
    written raises, and its partial file is removed."""
    log_path = Path(log_path)
    out = []
    for fmt in formats:
        if fmt == "log":
            continue
        path = log_path.with_suffix("." + fmt)
        tmp = path.with_suffix(".tmp." + fmt)     # (asammdf insists on its suffix)
        try:
            if fmt == "mf4":
                _write_mf4(log_path, tmp, start_us)
            else:
                writer = {"asc": lambda: _AscWriter(str(tmp), start_us),
                          "blf": lambda: can.io.BLFWriter(str(tmp)),
                          "trc": lambda: _TrcWriter(str(tmp), path.name)}[fmt]()
                try:
                    for msg in can.io.CanutilsLogReader(str(log_path)):
                        writer.on_message_received(msg)
                finally:
                    writer.stop()
            tmp.replace(path)
        finally:
            tmp.unlink(missing_ok=True)
        out.append(path)
    return out


def _write_mf4(log_path: Path, path: Path, start_us: int) -> None:
    """The frames as an ASAM MDF 4.10 bus-logging file (the CAN_DataFrame channel group of
    ASAM's bus-logging standard, as python-can's MF4Writer and Vector tools write it), in one
    block: times relative to the measurement's start, which the header carries."""
    from asammdf import MDF, Signal
    from asammdf.blocks.source_utils import Source
    from asammdf.blocks.v4_blocks import FileHistory
    from asammdf.blocks.v4_constants import BUS_TYPE_CAN, SOURCE_BUS
    from can.io.mf4 import STD_DTYPE

    msgs = list(can.io.CanutilsLogReader(str(log_path)))
    rows = np.zeros(len(msgs), dtype=STD_DTYPE)
    stamps = np.empty(len(msgs))
    start = start_us / 1e6
    for i, m in enumerate(msgs):
        rows[i]["CAN_DataFrame.BusChannel"] = can.util.channel2int(m.channel) or 0
        rows[i]["CAN_DataFrame.ID"] = m.arbitration_id
        rows[i]["CAN_DataFrame.DLC"] = rows[i]["CAN_DataFrame.DataLength"] = len(m.data)
        rows[i]["CAN_DataFrame.DataBytes"][:len(m.data)] = list(m.data)
        rows[i]["CAN_DataFrame.Dir"] = 0 if m.is_rx else 1
        stamps[i] = m.timestamp - start
    when = dt.datetime.fromtimestamp(start, dt.timezone.utc)
    mdf = MDF(version="4.10")
    mdf.header.start_time = when
    fh = FileHistory()
    fh.abs_time = start_us * 1000
    fh.comment = ("<FHcomment><TX>created from the bench's candump log</TX>"
                  "<tool_id>suspension-ecu hil</tool_id><tool_vendor>-</tool_vendor>"
                  "<tool_version>1</tool_version></FHcomment>")
    mdf.file_history.append(fh)
    source = Source(name="CAN", path="CAN", comment="", source_type=SOURCE_BUS,
                    bus_type=BUS_TYPE_CAN)
    mdf.append(Signal(name="CAN_DataFrame", samples=rows, timestamps=stamps, source=source),
               acq_name="CAN_DataFrame", acq_source=source)
    mdf.save(str(path), overwrite=True, add_history_block=False, compression=2)
    mdf.close()


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
