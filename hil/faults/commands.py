"""Faults of what the plant receives: actuator commands lost, forged without the key, or
replayed. A lost command is judged by the plant (its passive fallback); an attack by whether
every frame of it was stopped and had no effect."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from hil.faults.base import Evidence, Fault, Result, Window
from hil.nodes import ID

FORGED_DUTY = 0.88              # the forged commands' duty (the issue's attack)
HUB_DROPS = re.compile(r"\(read-only\): (\d+) frames it may not send dropped")


def forged_command(codec, counter: int, seq: int, salt: int) -> bytes:
    """An ACTUATOR_CMD as an attacker with the DBC but without the key builds it: 88 % duty,
    bridge enabled, the right SENSOR_SEQ, the COUNTER the receiver expects, a valid CRC, and
    MAC and freshness bytes that are a guess."""
    return codec.encode("ACTUATOR_CMD", {
        "DUTY": FORGED_DUTY, "REGEN": 0, "ENABLE": 1, "SENSOR_SEQ": seq,
        "FRESHNESS": salt & 0xFF, "MAC": (salt * 2654435761) & 0xFFFFFF}, counter)


@dataclass(frozen=True, kw_only=True)
class CommandLoss(Fault):
    """The plant's receiver loses every ACTUATOR_CMD: the plant must fall back to passive."""
    node: str = "plant_rx"

    def drop_rx(self, inj, plant, fid: int, w: Window) -> bool:
        if fid == ID["ACTUATOR_CMD"]:
            inj.mark(self.name, plant.k)
            return True
        return False

    def reaction(self, ev: Evidence) -> tuple:
        bad = ev.fallback[ev.seg]
        return np.flatnonzero(bad), bad, []

    def table_note(self, r: Result) -> str:
        return "(plant: passive fallback)"


@dataclass(frozen=True, kw_only=True)
class Attack(Fault):
    """Detected when every frame of it was stopped (dropped by the hub, or rejected by the
    plant's SecOC check), recovered when it had no effect at all: no passive fallback and no
    fail-safe tick in its window."""
    node: str = "plant_rx"

    def judge(self, ev: Evidence) -> Result:
        sent, seg = ev.applied[2], ev.seg
        rejected = np.asarray(ev.plant.get("rejected", np.zeros(0)))
        stopped = int(rejected[self.rejected_from(seg)].sum())
        note = f"{stopped} of {sent} rejected by the plant's SecOC check"
        if self.node == "bus" and ev.hub_log:         # (vcan0: no hub, no hub.log)
            dropped = sum(int(x) for x in HUB_DROPS.findall(ev.hub_log))
            stopped += dropped
            note = f"{dropped} of {sent} dropped at the hub (read-only client), " + note
        hit = sent > 0 and stopped >= sent
        clean = not np.any(ev.fallback[seg]) and bool(np.all(ev.enable[seg]))
        return Result(self.name, hit, 0 if hit else None, hit and clean, ev.crashed, True,
                      recovery_ticks=0 if hit and clean else None, fault_bits=[],
                      failsafe_ticks=int(np.count_nonzero(~ev.enable[seg])), note=note)

    def rejected_from(self, seg: slice) -> slice:
        return seg

    def table_note(self, r: Result) -> str:
        return r.note


@dataclass(frozen=True, kw_only=True)
class ForgedCommand(Attack):
    """A command forged without the key reaches the plant before every real one."""

    def rx_extra(self, inj, plant, w: Window) -> list:
        inj.mark(self.name, plant.k)
        return [forged_command(plant.codec, plant.expected_cmd_counter(),
                               plant.sensor_seq(), plant.k)]


@dataclass(frozen=True, kw_only=True)
class ReplayedCommand(Attack):
    """The command of ``REPLAY_AGE_TICKS`` earlier reaches the plant before every real one."""

    def rx_extra(self, inj, plant, w: Window) -> list:
        inj.mark(self.name, plant.k)
        return [inj.commands[0]]
