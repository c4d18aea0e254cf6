"""The supervisor's view of the bus: a logger thread that writes every frame to ``bus.log``,
knows each node's last frame (liveness), and the live view and progress line it feeds."""

from __future__ import annotations

import threading
import time
from typing import Optional


from firmware import safety
from firmware.params import GRADE_NAMES, MODE_NAMES
from hil.apps.driver import name_of
from hil.nodes import ID, LockstepClock
from hil.transport.buslog import BusLogFile
from hil.transport.codec import Codec, fault_word


class Logger(threading.Thread):
    """Writes every frame on the bus to the candump log; keeps the latest status for the
    live view."""

    def __init__(self, bus, log: BusLogFile, lockstep: bool, dt_s: float, codec: Codec,
                 t0: float):
        super().__init__(daemon=True)
        self.t0 = t0               # the run's start, monotonic (realtime stamps count from it)
        self.bus, self.log, self.codec = bus, log, codec
        self.clock = LockstepClock(dt_s) if lockstep else None
        self.ticks = 0
        self.view: dict = {}
        self.error: Optional[str] = None
        self._stop_evt = threading.Event()
        self._watch = {ID[n] for n in ("ECU_STATUS", "MODE_RECOMMEND", "ENERGY_STATUS",
                                       "SIM_TRUTH", "VEHICLE_SPEED", "DRIVER_REQUEST")}
        now = time.monotonic()
        self.last_seen: dict[int, float] = {}   # frame ID -> when last seen (monotonic)
        self.last_any, self.last_fid = now, None
        self.since = now                        # progress is watched from here

    def run(self) -> None:
        last_flush = time.monotonic()
        try:
            while not self._stop_evt.is_set():
                msg = self.bus.recv(0.1)
                now = time.monotonic()
                if now - last_flush > 0.5:
                    self.log.flush()
                    last_flush = now
                if msg is None:
                    continue
                fid, data = msg.arbitration_id, bytes(msg.data)
                self.last_seen[fid] = self.last_any = now
                self.last_fid = fid
                # realtime: the receive time here (candump semantics; senders' own stamps
                # interleave out of order when two nodes send independently), monotonic
                ts = self.clock.stamp(fid) if self.clock else now - self.t0
                self.log.write(fid, data, ts)
                if fid == ID["PLANT_SENSORS"]:
                    self.ticks += 1
                elif fid in self._watch:
                    d = self.codec.decode(fid, data)
                    if d.ok:
                        self.view.update({f"{d.name}.{k}": v for k, v in d.signals.items()})
        except Exception as exc:  # noqa: BLE001 - reported by the supervisor
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.log.flush()

    @property
    def kernel_drops(self) -> Optional[int]:
        """Frames the kernel dropped at the logger's socket (socketcan), None elsewhere."""
        return getattr(self.bus, "dropped", None)

    def drops_said(self) -> str:
        d = self.kernel_drops
        if d is None:
            return ""
        return (f" (the kernel dropped {d} at the logger's socket, whose buffer is "
                f"{self.bus.rcvbuf} bytes)" if d else " (the kernel reports no drop)")

    def seen(self, name: str) -> float:
        return self.last_seen.get(ID[name], self.since)

    def stalled(self, now: float, stall_s: float, realtime: bool) -> Optional[str]:
        """The node that has made no progress for ``stall_s``, or None. Lockstep: the bus
        fell silent; it was the turn of the node that must answer the last frame. Realtime:
        the plant sent no sensor frame, or the ECU no command, or the app left a
        recommendation unanswered, for that long."""
        if not realtime:
            if now - max(self.last_any, self.since) < stall_s:
                return None
            fid = self.last_fid
            if fid is None or fid == ID["ACTUATOR_CMD"]:
                return "plant"
            if fid == ID["MODE_RECOMMEND"]:
                return "app"
            return "ecu"
        if now - self.seen("PLANT_SENSORS") >= stall_s:
            return "plant"
        if now - self.seen("ACTUATOR_CMD") >= stall_s:
            return "ecu"
        if self.seen("MODE_RECOMMEND") - self.seen("DRIVER_REQUEST") >= stall_s:
            return "app"
        return None

    def wait_for(self, count: int, idle_s: float) -> bool:
        """True once the log holds ``count`` frames. The logger may be far behind the nodes
        (in User-mode Linux its socket queued 20,000 frames at the end of a long run, the
        kernel dropping none): it is given up on only when it has logged nothing for
        ``idle_s``, so a slow logger is waited for and a lost frame still fails the run (the
        wait is bounded by what the socket can hold)."""
        last, since = self.log.count, time.monotonic()
        while self.log.count < count and self.is_alive():
            now, n = time.monotonic(), self.log.count
            if n != last:
                last, since = n, now
            elif now - since >= idle_s:
                break
            time.sleep(0.02)
        return self.log.count >= count

    def stop(self) -> None:
        self._stop_evt.set()
        self.join(5.0)


def live_view(logger: Logger, n: int, dt: float, route, mode: str, pace: str):
    from rich.table import Table

    v = logger.view

    def mode_name(key):
        return name_of(MODE_NAMES, v.get(key), "-")

    def grade_name(key):
        return name_of(GRADE_NAMES, v.get(key), "?")

    t = Table(title=f"hil run: {route.name}, mode {mode}, {pace}", show_header=False)
    k = logger.ticks
    frac = k / n if n else 0.0
    bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
    t.add_row("progress", f"[{bar}] {100 * frac:5.1f} %  t = {k * dt:7.2f} / {n * dt:.1f} s")
    t.add_row("speed", f"{v.get('VEHICLE_SPEED.SPEED', 0.0):5.2f} m/s")
    t.add_row("grade (true / estimated)",
              f"{grade_name('SIM_TRUTH.TRUE_GRADE')} / {grade_name('ECU_STATUS.ESTIMATED_GRADE')}")
    t.add_row("recommended / active",
              f"{mode_name('MODE_RECOMMEND.RECOMMENDED_MODE')} / "
              f"{mode_name('ECU_STATUS.ACTIVE_MODE')}"
              + ("  (safety override)" if v.get("MODE_RECOMMEND.OVERRIDE") else ""))
    t.add_row("BA RMS / DTD RMS", f"{v.get('ECU_STATUS.BA_RMS', 0.0):.3f} m/s^2 / "
                                  f"{1e3 * v.get('ECU_STATUS.DTD_RMS', 0.0):.2f} mm")
    t.add_row("energy stored / drawn", f"{v.get('ENERGY_STATUS.STORED_ENERGY', 0.0):8.1f} J / "
                                       f"{v.get('ENERGY_STATUS.SUPPLY_ENERGY', 0.0):8.1f} J")
    t.add_row("faults", ", ".join(safety.fault_names(status_faults(v))) or "none")
    t.add_row("frames logged", f"{logger.log.count}")
    return t


def status_faults(view: dict) -> int:
    """The fault word of the last ECU_STATUS in the logger's view."""
    return fault_word({k.split(".", 1)[1]: x for k, x in view.items()
                       if k.startswith("ECU_STATUS.")})


def progress_line(logger: Logger, dt: float) -> str:
    """The progress line's detail without a terminal: time, grade, modes, faults."""
    v = logger.view
    word = status_faults(v)
    grade = v.get("ECU_STATUS.ESTIMATED_GRADE")
    rec, act = v.get("MODE_RECOMMEND.RECOMMENDED_MODE"), v.get("ECU_STATUS.ACTIVE_MODE")
    return (f"t = {logger.ticks * dt:.1f} s, grade {name_of(GRADE_NAMES, grade, '?')}, "
            f"recommended {name_of(MODE_NAMES, rec, '-')}, active {name_of(MODE_NAMES, act, '-')}"
            + (f", faults {', '.join(safety.fault_names(word))}" if word else ""))
