"""The injector: the nodes' hooks, dispatched to the fault family whose window is open."""

from __future__ import annotations

import json
from collections import deque
from pathlib import Path
from typing import Optional

from hil.faults.base import REPLAY_AGE_TICKS, Window
from hil.faults.registry import BY_NAME
from hil.nodes import Frame

SPAN_LEAD = REPLAY_AGE_TICKS + 50   # an injector's Python ticks before a window (spans)
SPAN_TAIL = 50                  # ... and after it


class Injector:
    """Applies the windows of one node (``plant`` or ``app``) through its hooks. ``applied``
    records, per fault, [first tick, last tick, frames touched]. Beside the windows it keeps
    what a family may need from before its window: the last frame of each message the plant
    sent, and the last ``REPLAY_AGE_TICKS`` commands it received."""

    def __init__(self, windows: list[Window], node: str, lockstep: bool = True):
        nodes = ("plant", "plant_rx", "plant_hw") if node == "plant" else (node,)
        self.windows = [w for w in windows if w.node in nodes]
        self.faults = {w.name: BY_NAME[w.name] for w in self.windows}
        self.lockstep = lockstep
        self.applied: dict[str, list[int]] = {}
        self.memo: dict[str, dict] = {}                       # per family (base.memo)
        self.last_sent: dict[int, bytes] = {}                 # frame ID -> its last payload
        self.commands: deque = deque(maxlen=REPLAY_AGE_TICKS)   # the last real commands

    @classmethod
    def from_file(cls, path: str, node: str, lockstep: bool = True) -> "Injector":
        data = json.loads(Path(path).read_text())
        return cls([Window(**w) for w in data["windows"]], node, lockstep)

    def spans(self) -> list[tuple[int, int]]:
        """The ticks [start, end) this injector needs the Python nodes for (the compiled SIL
        loop runs the rest, ``hil.nodes.fastsil``): each window, from ``SPAN_LEAD`` ticks
        before it (what it watches before: the commands a replay takes, the last VEHICLE_SPEED
        a flood repeats) to ``SPAN_TAIL`` after (the app's time, from ECU_STATUS, lags the
        plant's by up to a status period; the supply is set back the tick after)."""
        return [(max(0, w.start - SPAN_LEAD), w.start + w.ticks + SPAN_TAIL)
                for w in self.windows]

    def mark(self, name: str, k: int, n: int = 1) -> None:
        a = self.applied.setdefault(name, [k, k, 0])
        a[1] = k
        a[2] += n

    def _active(self, k: int, node: str) -> Optional[tuple]:
        for w in self.windows:
            if w.node == node and w.start <= k < w.start + w.ticks:
                return self.faults[w.name], w
        return None

    # -- the plant's hooks ----------------------------------------------------------------------

    def before_emit(self, plant) -> None:
        on = self._active(plant.k, "plant")
        if on is not None:
            on[0].before_emit(self, plant, on[1])

    def after_emit(self, plant, frames: list[Frame]) -> list[Frame]:
        for fid, data in frames:
            self.last_sent[fid] = data
        on = self._active(plant.k, "plant")
        return frames if on is None else on[0].after_emit(self, plant, list(frames), on[1])

    def hardware(self, plant, duty: int, regen: bool, enable: bool) -> tuple[int, bool, bool]:
        """The bridge, the winding and the supply as they are this tick: the command the
        corner actually gets (``plant.k``); the supply is nominal unless a fault says not."""
        plant.set_supply_voltage(plant.nominal_supply_v)
        on = self._active(plant.k, "plant_hw")
        if on is None:
            return duty, regen, enable
        self.mark(on[1].name, plant.k)
        return on[0].hardware(self, plant, (duty, regen, enable), on[1])

    def drop_rx(self, plant, fid: int) -> bool:
        on = self._active(plant.k, "plant_rx")
        return on is not None and on[0].drop_rx(self, plant, fid, on[1])

    def rx_extra(self, plant, data: bytes) -> list[bytes]:
        self.commands.append(data)
        on = self._active(plant.k, "plant_rx")
        return [] if on is None else on[0].rx_extra(self, plant, on[1])

    # -- the app's hook -------------------------------------------------------------------------

    def before_answer(self, app) -> None:
        on = self._active(app.t, "app")
        if on is not None:
            on[0].before_answer(self, app, on[1])
