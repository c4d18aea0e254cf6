"""Plausible sensor faults: a sensor that still reads inside its range, but wrong (biased,
drifting, off in gain, stuck). Only the model-based diagnostics can see them
(``firmware.diag.fdi``); they are judged on the DTCs the tester reads after the window too."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from calib.fdi_bank import CHANNEL
from firmware import safety
from firmware.diag import degrade as fd
from firmware.diag import dtc as fw
from hil.faults.base import (CAMPAIGN_SPEED_MPS, MAX_PLAUSIBLE_TICKS, PLAUSIBLE_TICKS,
                             SNAPSHOT_SPEED_TOL_MPS, Evidence, Fault, Result, Window, memo,
                             raw_signal, reencode)

SIGNAL = {"ba": "BODY_ACCEL_RAW", "wa": "WHEEL_ACCEL_RAW", "defl": "SUSP_DEFL_RAW",
          "current": "MOTOR_CURRENT_RAW"}


@dataclass(frozen=True, kw_only=True)
class Plausible(Fault):
    """A fault only a model sees: detected within ``limit`` ticks, its DTCs confirmed with a
    snapshot taken in the window at the drive's speed, and ``dtc`` among them where it claims
    isolation."""
    ticks: int = PLAUSIBLE_TICKS
    limit: int = MAX_PLAUSIBLE_TICKS
    expect: int = safety.FAULT_PLAUSIBILITY
    plausible: bool = True

    def judge(self, ev: Evidence) -> Result:
        r = super().judge(ev)
        judge_dtcs(r, self, ev.first, ev.window, ev.dtc_read)
        r.degraded = degraded_seen(ev)
        return r

    @property
    def degraded(self) -> str:
        """What degraded operation must do in the segment (``degraded_seen``): no sensor
        out for a fault of the actuator or the supply."""
        return "normal"

    @property
    def part(self) -> str:
        """The part this fault is of (``firmware.diag.dtc.PARTS``)."""
        return fw.DTCS[fw.BY_NAME[self.dtc]].part if self.dtc else ""

    def holds(self, r: Result) -> bool:
        return (super().holds(r) and bool(r.dtc) and r.snapshot_ok and r.isolated is not False
                and r.isolation != "wrong" and r.degraded == self.degraded)

    def limit_text(self, r: Result) -> str:
        return (super().limit_text(r) + ", DTC confirmed with its snapshot"
                + (f", {self.dtc}" if self.dtc else "") + f", degraded: {self.degraded}")

    def value_text(self, r: Result) -> str:
        return (super().value_text(r) + f"; DTC {', '.join(r.dtc or []) or 'none'}"
                + ("" if r.snapshot_ok else ", snapshot wrong or missing")
                + (f", isolation {r.isolation}" if r.isolation not in (None, "right") else "")
                + (f", degraded: {r.degraded}" if r.degraded != self.degraded else ""))


@dataclass(frozen=True, kw_only=True)
class SensorFault(Plausible):
    """A sensor's count on PLANT_SENSORS: ``bias`` (+``counts``), ``drift`` (``rate`` in the
    sensor's unit per second), ``gain`` (``gain`` around mid-scale), ``stuck`` (at the
    window's first count) or ``mid`` (stuck at mid-scale)."""
    channel: str = "ba"
    kind: str = "bias"
    counts: int = 0
    rate: float = 0.0
    gain: float = 1.0

    @property
    def part(self) -> str:
        return self.channel                       # (the channels are named as the parts)

    @property
    def degraded(self) -> str:
        """Its sensor out and the ECU driving on in the campaign's mode (comfort, kept
        without BA, WA or SWS); the motor current out: no mode, the bridge open."""
        return "out, bridge open" if self.channel == "current" else "out, driven on"

    def after_emit(self, inj, plant, frames, w: Window):
        sig = SIGNAL[self.channel]
        raw, full = raw_signal(plant.codec, frames[-1], sig)
        t = plant.k - w.start
        mid = (full + 1) // 2
        if self.kind == "bias":
            v = raw + self.counts
        elif self.kind == "gain":
            v = mid + round(self.gain * (raw - mid))
        elif self.kind == "drift":
            lsb = getattr(plant.cfg.sensors, CHANNEL[self.channel]).lsb
            v = raw + round(self.rate * t * plant.dt / lsb)
        elif self.kind == "mid":
            v = mid                               # (0 A: the current's range is symmetric)
        else:                                     # stuck at the first count of the window
            v = memo(inj, self).setdefault("held", raw)
        frames[-1] = reencode(plant.codec, frames[-1], **{sig: min(full, max(0, int(v)))})
        inj.mark(self.name, plant.k)
        return frames


def degraded_seen(ev: Evidence) -> str:
    """What degraded operation (``firmware.diag.degrade``) did in a fault's segment: "normal"
    (no sensor out), "out, driven on" (a sensor out and the bridge driven in the drive's
    mode meanwhile), "out, bridge open", "out" (neither), "out to the cycle's end",
    "fail-safe latched"."""
    d = ev.degraded[ev.seg]
    if (d == fd.STATE_FAIL_SAFE).any():
        return "fail-safe latched"
    if (d == fd.STATE_LATCHED).any():
        return "out to the cycle's end"
    out = d == fd.STATE_DEGRADED
    if not out.any():
        return "normal"
    enable, modes = ev.enable[ev.seg][out], ev.modes[ev.seg][out]
    if (enable & (modes == ev.mode)).any():
        return "out, driven on"
    return "out, bridge open" if not enable.any() else "out"


def isolation_of(names, part: str) -> Optional[str]:
    """What the confirmed DTCs ``names`` say of a fault of ``part``: "wrong" when any names a
    healthy part, "right" when they name it, "not isolated" when none names a part and the
    bank said so; None when none of them speaks to it."""
    parts = {fw.DTCS[fw.BY_NAME[n]].part for n in names} & set(fw.PARTS)
    if parts - {part}:
        return "wrong"
    if parts:
        return "right"
    return "not isolated" if "sensor_not_isolated" in names else None


def judge_dtcs(r: Result, spec: Fault, first: int, w: Window, read: Optional[dict]) -> None:
    """A plausible fault's DTCs as the tester read them over UDS after its window: its
    model-based DTCs confirmed, each with a snapshot taken inside the window at the drive's
    speed; ``isolation``: what the confirmed DTCs name (a wrong isolation is any that names a
    healthy part); ``isolated``: the faulty part named, where the fault claims it."""
    from hil.config import default_vehicle

    dt_ms = default_vehicle().sim.plant_dt_s * 1e3
    r.detect_ms = None if r.reaction_ticks is None else r.reaction_ticks * dt_ms
    if read is None or "error" in read:
        r.dtc = []
        r.note = (read or {}).get("error", "the DTCs were not read")
        r.snapshot_ok = False
        r.isolated = False if spec.dtc else None
        return
    got = [d for d in read["dtcs"] if d["status"] & 0x08]          # confirmed
    r.dtc = [f"{d['code']} {d['name']}" for d in got]
    # the fault's own DTCs are the model-based ones; a frame DTC beside them (bus_rate: the
    # driver app's request at the mode swap when the fail-safe ends) may fall after the window
    own = [d for d in got if fw.DTCS[fw.BY_NAME[d["name"]]].source == fw.SRC_TEST]
    r.snapshot_ok = bool(own) and all(
        "snapshot" in d and first <= d["snapshot"]["tick"] < w.start + w.ticks
        and d["snapshot"]["speed_mps"] is not None
        and abs(d["snapshot"]["speed_mps"] - CAMPAIGN_SPEED_MPS) <= SNAPSHOT_SPEED_TOL_MPS
        for d in own)
    r.isolation = isolation_of([d["name"] for d in got], spec.part)
    if spec.dtc:
        r.isolated = r.isolation == "right"
