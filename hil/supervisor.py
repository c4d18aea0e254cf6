"""``python -m hil run``: the bench as processes on a CAN bus.

Starts the hub (when the kernel has no vcan0), a logger on the bus (``DIR/bus.log``, every
frame), then the ECU and the driver app, then the plant, which owns simulated time. Shows a
live view, and when the plant has driven the route stops the ECU and the app, checks that the
log holds every frame the nodes report sending, and writes ``DIR/report.json`` (the schema of
``hil sim --json``), ``DIR/report.md`` and the figures. Ctrl-C or a node that dies stops
everything: nodes by PID, log flushed, a one-line reason, non-zero exit.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Optional

import numpy as np

from firmware.params import GRADE_NAMES, MODE_NAMES
from hil.bus import RT_PRIORITY, BusError, BusSpec, Hub, die_with_parent, resolve, rt_of
from hil.buslog import BusLogFile
from hil.codec import Codec
from hil import verdict
from hil.nodes import ID, LockstepClock, message_name

EXIT_NODE = 1
EXIT_INTERRUPTED = 130
READY_TIMEOUT_S = 60.0
NODES = ("ecu", "app", "plant")


class NodeFailure(RuntimeError):
    pass


class Node:
    """A node process started by the supervisor (stdout: READY line; stderr: DIR/<name>.log)."""

    def __init__(self, name: str, argv: list[str], out: Path):
        self.name = name
        self.errlog = out / f"{name}.log"
        self._err = open(self.errlog, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil", name, *argv], stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=self._err, start_new_session=True,
            preexec_fn=die_with_parent)
        self.ready = threading.Event()
        self.lines: deque = deque(maxlen=50)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            line = raw.decode(errors="replace").rstrip()
            if line == "READY":
                self.ready.set()
            else:
                self.lines.append(line)

    def wait_ready(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not self.ready.wait(0.05):
            if self.proc.poll() is not None:
                raise NodeFailure(f"node {self.name} exited at start with code "
                                  f"{self.proc.returncode}: {self.last_error()}")
            if time.monotonic() > deadline:
                raise NodeFailure(f"node {self.name} not ready within {timeout_s:g} s")

    def last_error(self) -> str:
        if not self._err.closed:
            self._err.flush()
        try:
            lines = [ln for ln in self.errlog.read_text(errors="replace").splitlines()
                     if ln.strip()]
        except OSError:
            lines = []
        return lines[-1] if lines else "(no message)"

    def stop(self, timeout_s: float = 10.0) -> Optional[int]:
        """SIGTERM, then SIGKILL after ``timeout_s``. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._err.close()
        return self.proc.returncode


class Logger(threading.Thread):
    """Writes every frame on the bus to the candump log; keeps the latest status for the
    live view."""

    def __init__(self, bus, log: BusLogFile, lockstep: bool, dt_s: float, codec: Codec):
        super().__init__(daemon=True)
        self.bus, self.log, self.codec = bus, log, codec
        self.clock = LockstepClock(dt_s) if lockstep else None
        self.ticks = 0
        self.view: dict = {}
        self.error: Optional[str] = None
        self._stop_evt = threading.Event()
        self._watch = {ID[n] for n in ("ECU_STATUS", "MODE_RECOMMEND", "ENERGY_STATUS",
                                       "SIM_TRUTH", "VEHICLE_SPEED", "DRIVER_REQUEST")}

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
                # realtime: the receive time here (candump semantics; senders' own stamps
                # interleave out of order when two nodes send independently)
                ts = self.clock.stamp(fid) if self.clock else time.time()
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

    def wait_for(self, count: int, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while self.log.count < count and time.monotonic() < deadline and self.is_alive():
            time.sleep(0.02)
        return self.log.count >= count

    def stop(self) -> None:
        self._stop_evt.set()
        self.join(5.0)


def _view(logger: Logger, n: int, dt: float, route, mode: str, pace: str):
    from rich.table import Table

    v = logger.view
    modes = MODE_NAMES
    grades = GRADE_NAMES

    def mode_name(key):
        x = v.get(key)
        return modes[int(x)] if x is not None and 0 <= int(x) < len(modes) else "-"

    def grade_name(key):
        x = v.get(key)
        return grades[int(x)] if x is not None and 0 <= int(x) < 4 else "?"

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
    t.add_row("fault bits", f"0x{int(v.get('ECU_STATUS.FAULTS', 0)):04X}")
    t.add_row("frames logged", f"{logger.log.count}")
    return t


def run(args) -> int:
    from hil.cli import design_or_exit, fail, route_or_exit, vehicle_or_exit
    from hil.config import ConfigError, load_driver_script

    cfg = vehicle_or_exit(args.vehicle)
    route = route_or_exit(args.route)
    design_or_exit(args.design)          # (checked here; the ECU node reads it)
    if args.script:
        try:
            load_driver_script(args.script)
        except ConfigError as exc:
            fail(str(exc))
    if args.driver == "script" and not args.script:
        fail("run: --driver script needs --script FILE")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from hil.figures import FIGURES

    stale = [f"{n}{x}" for n in NODES for x in (".json", ".npz", ".log")]
    for name in (*stale, "report.json", "report.md", *FIGURES):
        (out / name).unlink(missing_ok=True)   # a failed run leaves no old report behind
    dt = cfg.sim.plant_dt_s
    n = int(round(route.duration_s / dt))
    if args.duration is not None:
        n = min(n, int(round(args.duration / dt)))
    say = (lambda msg: print(msg, file=sys.stderr, flush=True))
    hub: Optional[Hub] = None
    nodes: dict[str, Node] = {}
    logger: Optional[Logger] = None
    log_bus = None
    code = 0
    t_start = time.monotonic()
    try:
        spec, needs_hub = resolve(getattr(args, "interface", None),
                                  getattr(args, "channel", None))
        rt = getattr(args, "rt_priority", None)
        if rt is None:
            rt = RT_PRIORITY if args.pace == "realtime" else 0
        if needs_hub:
            hub = Hub(rt_priority=rt_of(rt, "hub")).start()
            spec = BusSpec("remote", hub.url)
        assert spec is not None
        say(f"bus: {spec.interface} {spec.channel}  (watch: python -m can.viewer -i "
            f"{spec.interface} -c {spec.channel})")
        log_bus = spec.open()
        logger = Logger(log_bus, BusLogFile(out / "bus.log"), args.pace == "lockstep", dt,
                        Codec())
        logger.start()
        bus_args = ["-i", spec.interface, "-c", spec.channel]
        common = [*bus_args, "--out", str(out), "--pace", args.pace]
        if args.vehicle:
            common += ["--vehicle", args.vehicle]
        ecu_argv = [*common, "--mode", args.mode, "--rt-priority", str(rt_of(rt, "ecu"))]
        if args.controller:
            ecu_argv += ["--controller", args.controller]
        if args.gains:
            ecu_argv += ["--gains", args.gains]
        if args.design:
            ecu_argv += ["--design", args.design]
        if args.fixed_point:
            ecu_argv += ["--fixed-point"]
        app_argv = [*common, "--mode", args.mode, "--quiet", "--rt-priority",
                    str(rt_of(rt, "app"))]
        if args.driver:
            app_argv += ["--policy", args.driver]
        if args.script:
            app_argv += ["--script", args.script]
        plant_argv = [*common, "--route", args.route, "--seed", str(args.seed),
                      "--rt-priority", str(rt_of(rt, "plant"))]
        if getattr(args, "inject", None):       # hil faults: the injector's plan
            plant_argv += ["--inject", args.inject]
            app_argv += ["--inject", args.inject]
        if args.duration is not None:
            plant_argv += ["--duration", repr(args.duration)]
        for name, argv in (("ecu", ecu_argv), ("app", app_argv)):
            nodes[name] = Node(name, argv, out)
        for name in ("ecu", "app"):
            nodes[name].wait_ready(READY_TIMEOUT_S)
        nodes["plant"] = Node("plant", plant_argv, out)
        nodes["plant"].wait_ready(READY_TIMEOUT_S)
        _watch(nodes, logger, n, dt, route, args)
        for name in ("ecu", "app"):
            rc = nodes[name].stop()
            if rc not in (0, None):
                raise NodeFailure(f"node {name} exited with code {rc}: "
                                  f"{nodes[name].last_error()}")
        summaries = {name: json.loads((out / f"{name}.json").read_text()) for name in NODES}
        sent = sum(sum(s["frames_sent"].values()) for s in summaries.values())
        if not logger.wait_for(sent, 10.0):
            raise NodeFailure(f"bus.log holds {logger.log.count} frames, the nodes sent {sent}")
    except KeyboardInterrupt:
        say(f"interrupted at t = {logger.ticks * dt if logger else 0.0:.2f} s; nodes stopped, "
            f"{out / 'bus.log'} flushed")
        code = EXIT_INTERRUPTED
    except NodeFailure as exc:
        say(f"run failed: {exc}")
        code = EXIT_NODE
    except BusError as exc:
        say(f"run failed: {exc}")
        code = 3
    finally:
        for node in nodes.values():
            node.stop(5.0)
        if logger is not None:
            logger.stop()
            logger.log.close()
        if log_bus is not None:
            try:
                log_bus.shutdown()
            except Exception:  # noqa: BLE001 - the hub may be gone
                pass
        if hub is not None:
            hub.stop()
    if code:
        return code
    wall = time.monotonic() - t_start
    from hil import sil
    from hil.figures import write_outputs
    from hil.report import finish, render_sil

    plant_tr = dict(np.load(out / "plant.npz"))
    ecu_tr = dict(np.load(out / "ecu.npz"))
    trace = sil.merge_traces(dt, plant_tr, ecu_tr)
    report = sil.build_report(cfg, route, args.mode, args.controller, args.seed, trace,
                              summaries["plant"], summaries["ecu"], summaries["app"])
    report["bench"] = {"harness": "hil", "pace": args.pace, "bus": spec.interface,
                       "frames_logged": logger.log.count, "wall_s": wall,
                       "rtf": trace.segment.size * dt / wall}
    if args.pace == "realtime":
        report["bench"]["realtime"] = {k: summaries["plant"][k] for k in (
            "missed_deadlines", "missed_deadline_ratio", "lag_p50_us", "lag_p99_us",
            "lag_max_us", "overruns", "cmd_rtt_p50_us", "cmd_rtt_p99_us", "cmd_rtt_max_us",
            "sched")
            if k in summaries["plant"]}
    verdict.attach(report, run_checks(report, summaries, logger.log.by_id, n, dt, args,
                                      sil.fault_ticks(trace)))
    write_outputs(out, report, trace)
    if getattr(args, "junit", None):
        verdict.write_junit(args.junit, f"hil run {route.name} {args.mode} {args.pace}",
                            [verdict.Check(**c) for c in report["checks"]], wall)
    finish(report, None, "report.json", args.json, render_sil)
    if not args.json:
        print(f"report: {out / 'report.md'} (and report.json, bus.log, figures)")
    return verdict.exit_code(report)


def run_checks(report: dict, summaries: dict, logged_by_id: dict, n: int, dt: float,
               args, fault_ticks: int) -> list:
    """The verdict's checks of a bench run (``hil.verdict.run_checks``) from the nodes'
    summaries and the logger's count of frames per ID."""
    plant, ecu = summaries["plant"], summaries["ecu"]
    realtime = args.pace == "realtime"
    timer_ticks = ecu["frame_faults"].get("PLANT_SENSORS:missing", 0)
    ticks = {"PLANT": plant["ticks"]}
    if not realtime:     # realtime: the ECU's timer ticks too when a frame is late
        ticks["ECU"] = ecu["ticks"]
    sensors_sent = plant["frames_sent"].get("PLANT_SENSORS", 0)
    lost = max(0, sensors_sent - (ecu["ticks"] - timer_ticks))
    return verdict.run_checks(
        report, expected_ticks=n, dt_s=dt, ticks=ticks,
        bus_frames={message_name(fid): c for fid, c in logged_by_id.items()},
        pace=args.pace, injected=bool(getattr(args, "inject", None)),
        lost_sensor_frames=lost, missed_deadlines=plant.get("missed_deadlines", 0),
        fault_ticks=fault_ticks,
        limits=verdict.limits_of(args))


def _watch(nodes: dict, logger: Logger, n: int, dt: float, route, args) -> None:
    """Until the plant is done: a live view, and stop at the first node that dies."""
    live = None
    if not args.json and sys.stderr.isatty():
        from rich.console import Console
        from rich.live import Live

        live = Live(_view(logger, n, dt, route, args.mode, args.pace),
                    console=Console(stderr=True), refresh_per_second=4, transient=False)
        live.start()
    last_print = -1
    try:
        while True:
            plant_rc = nodes["plant"].proc.poll()
            for name in ("ecu", "app"):
                rc = nodes[name].proc.poll()
                if rc is not None:
                    raise NodeFailure(f"node {name} died (exit code {rc}) at t = "
                                      f"{logger.ticks * dt:.2f} s: {nodes[name].last_error()}")
            if logger.error:
                raise NodeFailure(f"logger lost the bus: {logger.error}")
            if plant_rc is not None:
                if plant_rc != 0:
                    raise NodeFailure(f"node plant exited with code {plant_rc} at t = "
                                      f"{logger.ticks * dt:.2f} s: "
                                      f"{nodes['plant'].last_error()}")
                return
            if live is not None:
                live.update(_view(logger, n, dt, route, args.mode, args.pace))
            elif not args.json:
                pct = int(10 * logger.ticks / max(1, n))
                if pct != last_print:
                    last_print = pct
                    print(f"  {10 * pct:3d} %  t = {logger.ticks * dt:7.2f} s",
                          file=sys.stderr, flush=True)
            time.sleep(0.1)
    finally:
        if live is not None:
            live.update(_view(logger, n, dt, route, args.mode, args.pace))
            live.stop()
