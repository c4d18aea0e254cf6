"""The ECU's diagnostic memory seen from Python, between ticks: the UDS server
(``firmware.diag.uds``) and the bench read and write the DTC rows of the state record
(``firmware.diag.dtc``) as objects (``entries[i].status``, ``.snapshot``, ...: a row's fields,
read and written through), the session as the server's own, and the last tick's values
(``view``: a tuple)."""

from __future__ import annotations

import numpy as np

from firmware.diag import SESSION_DEFAULT, degrade, dtc
from firmware.diag.dtc import Snapshot

_ROW = ("status", "fdc", "passes", "occurrences", "aging", "first_tick")


class EntryView:
    """One DTC's row (its fields, read and written through; ``snapshot`` as a ``Snapshot`` or
    None)."""

    __slots__ = ("_m", "_i")

    def __init__(self, mem, i: int):
        self._m, self._i = mem, i

    def __getattr__(self, name):
        if name in _ROW:
            return int(self._m[name][self._i])
        if name == "snapshot":
            if not self._m["has_snapshot"][self._i]:
                return None
            return Snapshot(*(int(v) for v in self._m["snapshot"][self._i]))
        raise AttributeError(name)

    def __setattr__(self, name, value):
        if name in EntryView.__slots__:
            object.__setattr__(self, name, value)
        elif name in _ROW:
            self._m[name][self._i] = value
        elif name == "snapshot":
            self._m["has_snapshot"][self._i] = value is not None
            self._m["snapshot"][self._i] = tuple(value) if value is not None else 0
        else:
            raise AttributeError(name)


class EntriesView:
    def __init__(self, mem):
        self._m = mem

    def __len__(self) -> int:
        return dtc.N

    def __getitem__(self, i: int) -> EntryView:
        if not -dtc.N <= i < dtc.N:
            raise IndexError(i)
        return EntryView(self._m, i % dtc.N)

    def __iter__(self):
        return (EntryView(self._m, i) for i in range(dtc.N))


class MemoryView:
    """The DTC memory: the record ``S.dtc``'s rows and flags (``record``: the record itself)."""

    _FLAGS = ("setting_on", "quiet", "tnc_done", "cycle")

    def __init__(self, mem):
        object.__setattr__(self, "record", mem)
        object.__setattr__(self, "entries", EntriesView(mem))

    def __getattr__(self, name):
        if name in MemoryView._FLAGS:
            value = self.record[name]
            return int(value) if name == "cycle" else bool(value)
        raise AttributeError(name)

    def __setattr__(self, name, value):
        if name not in MemoryView._FLAGS:
            raise AttributeError(name)
        self.record[name] = value


class DiagView:
    """What the UDS server reads and writes: the session is the server's (Python, between
    ticks); the DTC memory, the actuator test's supply reading and the last tick's values are
    the state record's."""

    def __init__(self, state):
        self._s = state[0]                     # the state record's element (np.void)
        self.fdi = state.view(np.recarray)[0].fdi   # (the fault-detection tests' state)
        self.dtc = MemoryView(self._s["dtc"])
        self.session = SESSION_DEFAULT
        self.session_tick = 0
        self.reset_requested = 0

    def clear(self, group: int) -> bool:
        """ClearDiagnosticInformation (``firmware.diag.dtc.clear``): False where there is no
        such group. A clear of every DTC (the workshop's) also starts the count of each
        sensor's namings afresh (``firmware.diag.degrade``: a sensor named again after it is
        not latched out by the earlier ones); what is out now stays out."""
        if not dtc.clear(self.dtc, group):
            return False
        if group == 0xFFFFFF:
            self._s["degrade"]["named"][:] = 0
        return True

    @property
    def degraded(self) -> tuple:
        """(state, sensor out, the tick it went out, the second fault's tick): -1 for none
        (``firmware.diag.degrade``)."""
        d = self._s["degrade"]
        state = degrade.code(bool(d["failsafe"]), int(d["sensor"]), bool(d["latched"]))
        return state, int(d["sensor"]), int(d["since"]), int(d["second"])

    @property
    def view(self) -> tuple:
        last = self._s["last"]
        return tuple(int(last[n]) for n in ("mode", "grade", "faults", "speed",
                                             "ba_rms_mmps2", "dtd_rms_um", "tick",
                                             "supply_mv"))

