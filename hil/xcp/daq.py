"""Dynamic DAQ: lists of ODTs of entries, allocated by the master, sampled at the boundary
of their event's tick (event 0 every tick, event 1 every tenth), one DTO per ODT with the
absolute ODT number as its PID and, on a list's first ODT, the ECU's time in us (the tick
times 1000: lockstep runs give the same bytes).

The bus budget: a list starts only if the DAQ's frames, with the DBC's own traffic, keep the
bus at or under ``BUDGET`` of its bit rate (ERR_DAQ_CONFIG otherwise); each DTO counts as a
classic 8-byte frame with worst-case bit stuffing (``hil.transport.busload``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from calib.a2l import EVENTS, MAX_DAQ, MAX_DTO, MAX_ODT_ENTRY_SIZE
from hil.transport.busload import frame_bits
from hil.xcp.protocol import (ERR_DAQ_ACTIVE, ERR_DAQ_CONFIG, ERR_MEMORY_OVERFLOW,
                              ERR_MODE_NOT_VALID, ERR_OUT_OF_RANGE, ERR_SEQUENCE, XcpError)

BUDGET = 0.80
TIMESTAMP_SIZE = 4
MAX_PID = 0xFB                  # 0xFC..0xFF are SERV, EV, ERR, RES
MAX_ENTRIES = 7                 # per ODT (one byte each at least)
MODE_DIRECTION_STIM, MODE_TIMESTAMP, MODE_PID_OFF = 0x02, 0x10, 0x20


def list_bits_per_s(odts: int, event: int, prescaler: int) -> float:
    """What a running DAQ list puts on the bus: one DTO per ODT (``odts``) at every
    ``prescaler``-th occurrence of event channel ``event``, each DTO an 8-byte classic frame
    (``tools.busload --daq`` counts a planned list with this)."""
    return odts * frame_bits(MAX_DTO) * 1000.0 / (EVENTS[event][3] * prescaler)


@dataclass
class DaqList:
    odts: list = field(default_factory=list)     # per ODT: entries (record, offset, size)
    sizes: list = field(default_factory=list)    # per ODT: its entry count allocated
    event: int = 0
    prescaler: int = 1
    priority: int = 0
    mode: int = 0
    selected: bool = False
    running: bool = False
    first_pid: int = 0
    count: int = 0                               # event occurrences seen (the prescaler)


class Daq:
    def __init__(self, memory, base_bits_per_s: float, bitrate: float):
        self.memory = memory
        self.base_bits, self.bitrate = base_bits_per_s, bitrate
        self.lists: list[DaqList] = []
        self.stage = 0          # 0 free, 1 lists allocated, 2 ODTs, 3 entries
        self.ptr = None         # (list, odt, entry) of SET_DAQ_PTR
        self.dtos = 0           # DTOs sent

    @property
    def running(self) -> bool:
        return any(d.running for d in self.lists)

    def free(self) -> None:
        if self.running:
            raise XcpError(ERR_DAQ_ACTIVE, "stop the DAQ before freeing it")
        self.lists, self.stage, self.ptr = [], 0, None

    def alloc_daq(self, n: int) -> None:
        if self.stage != 0:
            raise XcpError(ERR_SEQUENCE, "ALLOC_DAQ comes right after FREE_DAQ")
        if not 0 < n <= MAX_DAQ:
            raise XcpError(ERR_MEMORY_OVERFLOW, f"{n} DAQ lists (at most {MAX_DAQ})")
        self.lists, self.stage = [DaqList() for _ in range(n)], 1

    def _list(self, i: int) -> DaqList:
        if not 0 <= i < len(self.lists):
            raise XcpError(ERR_OUT_OF_RANGE, f"no DAQ list {i}")
        return self.lists[i]

    def alloc_odt(self, i: int, n: int) -> None:
        if self.stage not in (1, 2):
            raise XcpError(ERR_SEQUENCE, "ALLOC_ODT comes after ALLOC_DAQ")
        d = self._list(i)
        if d.sizes:
            raise XcpError(ERR_SEQUENCE, f"DAQ list {i} has its ODTs already")
        if n <= 0 or sum(len(x.sizes) for x in self.lists) + n > MAX_PID + 1:
            raise XcpError(ERR_MEMORY_OVERFLOW, f"{n} ODTs: the PIDs run out")
        d.sizes, d.odts, self.stage = [0] * n, [[] for _ in range(n)], 2
        pid = 0
        for x in self.lists:
            x.first_pid, pid = pid, pid + len(x.sizes)

    def alloc_entry(self, i: int, j: int, n: int) -> None:
        if self.stage not in (2, 3):
            raise XcpError(ERR_SEQUENCE, "ALLOC_ODT_ENTRY comes after ALLOC_ODT")
        d = self._list(i)
        if not 0 <= j < len(d.sizes):
            raise XcpError(ERR_OUT_OF_RANGE, f"no ODT {j} in DAQ list {i}")
        if not 0 <= n <= MAX_ENTRIES:      # (0: a first ODT with room for its timestamp only)
            raise XcpError(ERR_MEMORY_OVERFLOW, f"{n} entries (at most {MAX_ENTRIES})")
        d.sizes[j], d.odts[j], self.stage = n, [None] * n, 3

    def set_ptr(self, i: int, j: int, k: int) -> None:
        d = self._list(i)
        if d.running:
            raise XcpError(ERR_DAQ_ACTIVE, f"DAQ list {i} is running")
        if not (0 <= j < len(d.sizes) and 0 <= k < d.sizes[j]):
            raise XcpError(ERR_OUT_OF_RANGE, f"no entry {k} of ODT {j} in DAQ list {i}")
        self.ptr = (i, j, k)

    def write(self, bit_offset: int, size: int, address: int) -> None:
        if self.ptr is None:
            raise XcpError(ERR_SEQUENCE, "WRITE_DAQ without SET_DAQ_PTR")
        i, j, k = self.ptr
        d = self.lists[i]
        if k >= d.sizes[j]:
            raise XcpError(ERR_OUT_OF_RANGE, f"ODT {j} of DAQ list {i} is full")
        if bit_offset != 0xFF:
            raise XcpError(ERR_OUT_OF_RANGE, "bit-wise entries are not supported")
        if not 0 < size <= MAX_ODT_ENTRY_SIZE:
            raise XcpError(ERR_OUT_OF_RANGE, f"entry of {size} bytes")
        record, offset = self.memory.readable(address, size)
        d.odts[j][k] = (record, offset, size)
        self.ptr = (i, j, k + 1)

    def set_mode(self, mode: int, i: int, event: int, prescaler: int, priority: int) -> None:
        d = self._list(i)
        if d.running:
            raise XcpError(ERR_DAQ_ACTIVE, f"DAQ list {i} is running")
        if mode & (MODE_DIRECTION_STIM | MODE_PID_OFF):
            raise XcpError(ERR_MODE_NOT_VALID, "STIM and PID_OFF are not supported")
        if not 0 <= event < len(EVENTS):
            raise XcpError(ERR_OUT_OF_RANGE, f"no event channel {event}")
        if prescaler < 1:
            raise XcpError(ERR_OUT_OF_RANGE, "prescaler 0")
        d.mode, d.event, d.prescaler, d.priority = mode | MODE_TIMESTAMP, event, prescaler, priority

    def _check(self, d: DaqList, i: int) -> None:
        for j, (n, entries) in enumerate(zip(d.sizes, d.odts)):
            room = MAX_DTO - 1 - (TIMESTAMP_SIZE if j == 0 else 0)
            written = [e for e in entries if e is not None]
            if not d.sizes or len(written) != n or sum(e[2] for e in written) > room:
                raise XcpError(ERR_DAQ_CONFIG, f"ODT {j} of DAQ list {i}: {len(written)} of "
                                               f"{n} entries written, {room} bytes of room")

    def bits_per_s(self, lists) -> float:
        """What these lists put on the bus."""
        return sum(list_bits_per_s(len(d.sizes), d.event, d.prescaler) for d in lists)

    def load(self) -> float:
        """The bus load with the running lists."""
        return (self.base_bits + self.bits_per_s([d for d in self.lists if d.running])) \
            / self.bitrate

    def _budget(self, starting) -> None:
        lists = {id(d): d for d in self.lists if d.running}
        lists.update({id(d): d for d in starting})
        load = (self.base_bits + self.bits_per_s(lists.values())) / self.bitrate
        if load > BUDGET:
            raise XcpError(ERR_DAQ_CONFIG, f"the bus would carry {load:.1%} of "
                                           f"{self.bitrate / 1000:g} kbit/s (at most "
                                           f"{BUDGET:.0%})")

    def start_stop(self, mode: int, i: int) -> int:
        d = self._list(i)
        if mode == 0:
            d.running = d.selected = False
        elif mode in (1, 2):
            self._check(d, i)
            if mode == 1:
                self._budget([d])
                d.running, d.count = True, 0
            else:
                d.selected = True
        else:
            raise XcpError(ERR_MODE_NOT_VALID, f"START_STOP_DAQ_LIST mode {mode}")
        return d.first_pid

    def synch(self, mode: int) -> None:
        if mode == 0:
            for d in self.lists:
                d.running = d.selected = False
        elif mode == 1:
            chosen = [d for d in self.lists if d.selected]
            self._budget(chosen)
            for d in chosen:
                d.running, d.selected, d.count = True, False, 0
        elif mode == 2:
            for d in self.lists:
                if d.selected:
                    d.running = d.selected = False
        else:
            raise XcpError(ERR_MODE_NOT_VALID, f"START_STOP_SYNCH mode {mode}")

    def sample(self, tick: int) -> list[bytes]:
        """The DTOs of the events at the end of ``tick`` (event 1: every tenth tick)."""
        out = []
        for d in self.lists:
            if not d.running or tick % EVENTS[d.event][3]:
                continue
            d.count += 1
            if (d.count - 1) % d.prescaler:
                continue
            stamp = (tick * 1000) & 0xFFFFFFFF
            for j, entries in enumerate(d.odts):
                parts = [bytes([d.first_pid + j])]
                if j == 0:
                    parts.append(stamp.to_bytes(TIMESTAMP_SIZE, "little"))
                parts += [self.memory.sample(r, off, n) for r, off, n in entries]
                out.append(b"".join(parts))
        self.dtos += len(out)
        return out
