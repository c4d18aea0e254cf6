"""Faults of the plant's hardware: the bridge's PWM stuck, the winding open, the supply low.
Plausible faults too: the ECU's actuator test and supply monitor see them, within 20 ms."""

from __future__ import annotations

from dataclasses import dataclass

from hil.faults.base import MAX_ACTUATOR_TICKS, Window
from hil.faults.sensors import Plausible


@dataclass(frozen=True, kw_only=True)
class Hardware(Plausible):
    node: str = "plant_hw"
    limit: int = MAX_ACTUATOR_TICKS


@dataclass(frozen=True, kw_only=True)
class StuckDuty(Hardware):
    """The bridge's PWM stuck at ``duty`` while it is enabled."""
    duty: float = 0.6

    def hardware(self, inj, plant, cmd: tuple, w: Window) -> tuple:
        duty, regen, enable = cmd
        return (round(self.duty * 32768) if enable else duty), regen, enable


@dataclass(frozen=True, kw_only=True)
class OpenWinding(Hardware):
    """The winding carries no current: as an open bridge."""

    def hardware(self, inj, plant, cmd: tuple, w: Window) -> tuple:
        return cmd[0], cmd[1], False


@dataclass(frozen=True, kw_only=True)
class SupplyDrop(Hardware):
    """The supply falls to ``share`` of nominal."""
    share: float = 0.6

    def hardware(self, inj, plant, cmd: tuple, w: Window) -> tuple:
        plant.set_supply_voltage(plant.nominal_supply_v * self.share)
        return cmd
