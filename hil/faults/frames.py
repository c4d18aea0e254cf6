"""Faults of what the plant sends: lost frames, a broken CHECKSUM, COUNTER or DLC, a signal
forced to a value, a frame the DBC does not know, a message sent too often."""

from __future__ import annotations

from dataclasses import dataclass

from hil.faults.base import Fault, Window, name_of, reencode
from hil.nodes import ID


@dataclass(frozen=True, kw_only=True)
class FrameLoss(Fault):
    """The plant's PLANT_SENSORS frames (``everything``: all its frames) never reach the bus.
    In lockstep the plant says on the simulated bus that its tick passed (SIM_TICK)."""
    everything: bool = False

    def after_emit(self, inj, plant, frames, w: Window):
        dropped = [f for f in frames if self.everything or f[0] == ID["PLANT_SENSORS"]]
        out = [f for f in frames if f not in dropped]
        plant.withdraw([fid for fid, _ in dropped])
        if inj.lockstep:   # the ECU's timer still ticks: say so on the simulated bus
            out.append(plant.encode("SIM_TICK", {"TICK": plant.k & 0xFF}))
        inj.mark(self.name, plant.k, len(dropped))
        return out


@dataclass(frozen=True, kw_only=True)
class CorruptChecksum(Fault):
    """PLANT_SENSORS with its CHECKSUM byte flipped."""

    def after_emit(self, inj, plant, frames, w: Window):
        fid, data = frames[-1]
        cb = plant.codec.specs[fid].checksum_byte
        frames[-1] = (fid, data[:cb] + bytes([data[cb] ^ 0x5A]) + data[cb + 1:])
        inj.mark(self.name, plant.k)
        return frames


@dataclass(frozen=True, kw_only=True)
class CounterSkip(Fault):
    """PLANT_SENSORS's COUNTER moved by ``step`` before the frame is built (-1: repeated)."""
    step: int = 1

    def before_emit(self, inj, plant, w: Window) -> None:
        plant.shift_counter("PLANT_SENSORS", self.step)
        inj.mark(self.name, plant.k)


@dataclass(frozen=True, kw_only=True)
class ShortFrame(Fault):
    """PLANT_SENSORS one byte short (DLC 7 instead of 8)."""

    def after_emit(self, inj, plant, frames, w: Window):
        fid, data = frames[-1]
        frames[-1] = (fid, data[:-1])
        inj.mark(self.name, plant.k)
        return frames


@dataclass(frozen=True, kw_only=True)
class SignalForced(Fault):
    """A signal of the plant's frames held at one raw value (CHECKSUM resealed: the sender
    is faulty, not the wire)."""
    message: str = "PLANT_SENSORS"
    signal: str = ""
    raw: int = 0

    def after_emit(self, inj, plant, frames, w: Window):
        for i, f in enumerate(frames):
            if f[0] == ID[self.message]:
                frames[i] = reencode(plant.codec, f, **{self.signal: self.raw})
                inj.mark(self.name, plant.k)
        return frames


@dataclass(frozen=True, kw_only=True)
class UnknownFrame(Fault):
    """A frame with an ID the DBC does not define, every tick before PLANT_SENSORS."""
    frame_id: int = 0x123

    def after_emit(self, inj, plant, frames, w: Window):
        frames.insert(len(frames) - 1, (self.frame_id, bytes(range(8))))
        plant.count_sent(f"0x{self.frame_id:X}")
        inj.mark(self.name, plant.k)
        return frames


@dataclass(frozen=True, kw_only=True)
class Flood(Fault):
    """``message`` sent every tick (again, with the last values it carried)."""
    message: str = "VEHICLE_SPEED"

    def after_emit(self, inj, plant, frames, w: Window):
        fid = ID[self.message]
        last = inj.last_sent.get(fid)
        if any(f[0] == fid for f in frames) or last is None:
            return frames
        raw = plant.codec.decode(fid, last, scaling=False).signals
        frames.insert(0, plant.encode(name_of(plant.codec, fid), raw))
        inj.mark(self.name, plant.k)
        return frames
