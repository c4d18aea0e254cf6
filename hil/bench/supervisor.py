"""``python -m hil run``: the bench as processes on a CAN bus.

Starts the hub (when the kernel has no vcan0), a logger on the bus (``DIR/bus.log``, every
frame), then the ECU and the driver app, then the plant, which owns simulated time. Shows a
live view, and when the plant has driven the route stops the ECU and the app, checks that the
log holds every frame the nodes report sending, and writes ``DIR/report.json`` (the schema of
``hil sim --json``), ``DIR/report.md`` and the figures, with the run's verdict. Ctrl-C,
SIGTERM, SIGHUP, a node that dies and a node (or the hub) that makes no progress for
``--stall-s`` each stop everything the same way: nodes by PID, the bus closed in bounded
time, the log flushed, a one-line reason, a partial report marked ``incomplete``, non-zero
exit. ``--out`` is locked for the run.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Optional

import numpy as np

from firmware import safety
from firmware.params import GRADE_NAMES, MODE_NAMES
from hil.transport import secoc
from hil.nodes import sil
from hil.report import verdict
from hil.transport.auth import SECRET_ENV
from hil.transport.bus import (RT_PRIORITY, BusError, BusSpec, Hub, SocketcanTap, close_bus,
                     die_with_parent, resolve, rt_of, terminate)
from hil.transport.buslog import HUB_CHANNEL, LOG_FORMATS, BusLogFile, convert
from hil.transport.codec import Codec, fault_word
from hil.apps.driver import name_of
from hil.nodes import ID, LockstepClock, message_name

EXIT_NODE = 1
EXIT_INTERRUPTED = 130
READY_IDLE_S = 30.0          # a starting node that uses no CPU for this long is stuck
READY_CAP_S = 900.0          # and none may take longer than this to start (cold caches, UML)
STALL_S = 20.0               # no progress for this long stops the run (--stall-s)
NODES = ("ecu", "app", "plant")


class NodeFailure(RuntimeError):
    pass


class Node:
    """A node process started by the supervisor (stdout: READY line; stderr: DIR/<name>.log)."""

    def __init__(self, name: str, argv: list[str], out: Path, env: Optional[dict] = None):
        self.name = name
        self.errlog = out / f"{name}.log"
        self._err = open(self.errlog, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil", name, *argv], stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=self._err, start_new_session=True,
            preexec_fn=die_with_parent, env=env)
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

    def wait_ready(self, idle_s: float = READY_IDLE_S, cap_s: float = READY_CAP_S) -> None:
        """Until the node prints READY. Starting means importing and loading (or, on a cold
        cache, compiling) the numba kernels, which takes from a second to minutes (three
        nodes compiling on UML's one CPU); so the wait is on progress, not a fixed time: the
        node fails when its CPU time stops advancing for ``idle_s`` (it is stuck, e.g. on a
        bus that never answers) or after ``cap_s`` in all."""
        start = time.monotonic()
        cpu, since = _cpu_time(self.proc.pid), start
        while not self.ready.wait(0.05):
            if self.proc.poll() is not None:
                raise NodeFailure(f"node {self.name} exited at start with code "
                                  f"{self.proc.returncode}: {self.last_error()}")
            now = time.monotonic()
            used = _cpu_time(self.proc.pid)
            if used > cpu:
                cpu, since = used, now
            if now - since > idle_s:
                raise NodeFailure(f"node {self.name} not ready: no progress (CPU time) for "
                                  f"{idle_s:g} s after {now - start:.0f} s")
            if now - start > cap_s:
                raise NodeFailure(f"node {self.name} not ready within {cap_s:g} s")

    def last_error(self) -> str:
        if not self._err.closed:
            self._err.flush()
        try:
            lines = [ln for ln in self.errlog.read_text(errors="replace").splitlines()
                     if ln.strip()]
        except OSError:
            lines = []
        return lines[-1] if lines else "(no message)"

    def terminate(self) -> None:
        terminate(self.proc)

    def stop(self, timeout_s: float = 10.0) -> Optional[int]:
        """SIGTERM, then SIGKILL after ``timeout_s``. Returns the exit code."""
        if self.proc.poll() is None:
            self.terminate()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._err.close()
        return self.proc.returncode


def _proc_stat(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command name (state first); [] if unreadable."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2:].split()
    except (OSError, ValueError):
        return []


def _cpu_time(pid: int) -> float:
    """User + system CPU seconds of a process, 0.0 when unreadable."""
    fields = _proc_stat(pid)
    try:
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (ValueError, IndexError):
        return 0.0


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
    t.add_row("faults", ", ".join(safety.fault_names(_status_faults(v))) or "none")
    t.add_row("frames logged", f"{logger.log.count}")
    return t


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, SIGTERM or SIGHUP: the run stops the same way for each."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _on_signals():
    """SIGTERM and SIGHUP raise like Ctrl-C (once; a repeat during the cleanup is ignored).
    Returns the previous handlers."""
    fired = []

    def handler(signum, _frame):
        if not fired:
            fired.append(signum)
            raise Interrupted(signum)

    return {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGHUP)}


def _check_inputs(args):
    from hil.cli import design_or_exit, fail, route_or_exit, vehicle_or_exit
    from hil.config import ConfigError, load_driver_script

    cfg = vehicle_or_exit(args.vehicle)
    route = route_or_exit(args.route)
    design_or_exit(args.design)          # (checked here; the ECU node reads it)
    try:
        sil.check_route(cfg, route)
        if args.script:
            load_driver_script(args.script)
        if args.gains:
            from calib.ecu_params import load_gains

            load_gains(Path(args.gains), cfg)
    except ConfigError as exc:
        fail(str(exc))
    if args.driver == "script" and not args.script:
        fail("run: --driver script needs --script FILE")
    if args.driver == "interactive":
        fail("run: --driver interactive needs the app's own terminal, which the bench's nodes "
             "do not have: use --driver web (a page on 127.0.0.1), or start python -m hil app "
             "--policy interactive beside the nodes")
    return cfg, route


def _node_argvs(args, spec: BusSpec, out: Path, rt: int, key_file: Path
                ) -> dict[str, list[str]]:
    common = ["-i", spec.interface, "-c", spec.channel, "--out", str(out), "--pace", args.pace,
              "--key-file", str(key_file)]
    if args.vehicle:
        common += ["--vehicle", args.vehicle]
    ecu = [*common, "--mode", args.mode, "--rt-priority", str(rt_of(rt, "ecu"))]
    for flag, value in (("--controller", args.controller), ("--gains", args.gains),
                        ("--design", args.design)):
        if value:
            ecu += [flag, value]
    if args.fixed_point:
        ecu += ["--fixed-point"]
    app = [*common, "--mode", args.mode, "--quiet", "--rt-priority", str(rt_of(rt, "app"))]
    if args.driver:
        app += ["--policy", args.driver]
    if args.driver == "web":
        app += ["--web-port", str(getattr(args, "web_port", 0) or 0)]
    if args.script:
        app += ["--script", args.script]
    plant = [*common, "--route", args.route, "--seed", str(args.seed),
             "--rt-priority", str(rt_of(rt, "plant"))]
    if getattr(args, "inject", None):       # hil faults: the injector's plan
        plant += ["--inject", args.inject]
        app += ["--inject", args.inject]
    if args.duration is not None:
        plant += ["--duration", repr(args.duration)]
    return {"ecu": ecu, "app": app, "plant": plant}


def run(args, on_bus=None) -> int:
    """``on_bus(spec)``: called once the bus is up, before the nodes start (the fault
    campaign attaches its outside client there)."""
    from hil.cli import lock_out, log_options_or_exit

    cfg, route = _check_inputs(args)
    if getattr(args, "pace", None) is None:    # a person at the page drives at the car's pace
        args.pace = "realtime" if args.driver == "web" else "lockstep"
    start_us, formats = log_options_or_exit(args)
    t0 = time.monotonic()                # (the moment of start_us, on the monotonic clock)
    out = lock_out(args.out)
    from hil.report.figures import FIGURES

    stale = [f"{n}{x}" for n in NODES for x in (".json", ".npz", ".log")]
    copies = [f"bus.{x}" for x in LOG_FORMATS if x != "log"]
    for name in (*stale, *copies, "app.url", "hub.log", "report.json", "report.md", secoc.KEY_FILE_NAME,
                 HUB_SECRET_FILE, *FIGURES):
        (out / name).unlink(missing_ok=True)   # a failed run leaves no old report behind
    key_file = _key_file(args, out)
    dt = cfg.sim.plant_dt_s
    n = int(round(route.duration_s / dt))
    if args.duration is not None:
        n = min(n, int(round(args.duration / dt)))
    say = (lambda msg: print(msg, file=sys.stderr, flush=True))
    hub: Optional[Hub] = None
    nodes: dict[str, Node] = {}
    logger: Optional[Logger] = None
    log_bus = None
    code, reason = 0, None
    t_start = time.monotonic()
    previous = _on_signals()
    try:
        spec, needs_hub = resolve(getattr(args, "interface", None),
                                  getattr(args, "channel", None))
        rt = getattr(args, "rt_priority", None)
        if rt is None:
            rt = RT_PRIORITY if args.pace == "realtime" else 0
        env = {k: v for k, v in os.environ.items() if k != SECRET_ENV}
        if needs_hub:
            # the run's secret: to the hub and the nodes in their environment, never argv
            env[SECRET_ENV] = secrets.token_hex(16)
            # (for a tester, hil diag --secret-file: a key file, mode 0600, never argv)
            secoc.write_key(out / HUB_SECRET_FILE, bytes.fromhex(env[SECRET_ENV]))
            hub = Hub(rt_priority=rt_of(rt, "hub"), secret=env[SECRET_ENV],
                      allow_external_tx=getattr(args, "allow_external_tx", False),
                      allow_unknown_ids=bool(getattr(args, "inject", None)),
                      log_path=out / "hub.log").start()
            spec = BusSpec("remote", hub.url)
        assert spec is not None
        say(f"bus: {spec.interface} {spec.channel}  (watch: python -m can.viewer -i "
            f"{spec.interface} -c {spec.channel})")
        log_bus = SocketcanTap(spec.channel) if spec.interface == "socketcan" else spec.open()
        channel = spec.channel if spec.interface == "socketcan" else HUB_CHANNEL
        logger = Logger(log_bus, BusLogFile(out / "bus.log", channel, start_us),
                        args.pace == "lockstep", dt, Codec(), t0)
        logger.start()
        if on_bus is not None:
            on_bus(spec)
        argvs = _node_argvs(args, spec, out, rt, key_file)
        for name in ("ecu", "app"):
            nodes[name] = Node(name, argvs[name], out, env)
        for name in ("ecu", "app"):
            nodes[name].wait_ready()
        if args.driver == "web":
            say(f"driver page: {(out / 'app.url').read_text().strip()}  (the driver app: "
                "accept, refuse or choose a mode there)")
        nodes["plant"] = Node("plant", argvs["plant"], out, env)
        nodes["plant"].wait_ready()
        _watch(nodes, hub, logger, n, dt, route, args)
        for name in ("ecu", "app"):
            rc = nodes[name].stop()
            if rc not in (0, None):
                raise NodeFailure(f"node {name} exited with code {rc}: "
                                  f"{nodes[name].last_error()}")
        summaries = {name: json.loads((out / f"{name}.json").read_text()) for name in NODES}
        _count_tester(args, logger)
        sent = sum(sum(s["frames_sent"].values()) for s in summaries.values()) + sum(
            (getattr(args, "outside_frames", None) or {}).values())
        if not logger.wait_for(sent, 10.0):
            raise NodeFailure(f"bus.log holds {logger.log.count} frames, the nodes sent {sent}"
                              + logger.drops_said())
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
        what = "" if signum == signal.SIGINT else f" ({signal.Signals(signum).name})"
        reason = (f"interrupted{what} at t = {logger.ticks * dt if logger else 0.0:.2f} s")
        say(f"{reason}; nodes stopped, {out / 'bus.log'} flushed")
        code = EXIT_INTERRUPTED if signum == signal.SIGINT else 128 + signum
    except NodeFailure as exc:
        reason = str(exc)
        say(f"run failed: {exc}")
        code = EXIT_NODE
    except BusError as exc:
        reason = str(exc)
        say(f"run failed: {exc}")
        code = 3
    finally:
        _shut_down(nodes, logger, log_bus, hub)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    try:
        logs = _copies(logger, formats, start_us, say)
        if logs is None and not code:
            code, reason = EXIT_NODE, "the bus log could not be converted"
        if code:
            _partial_report(out, cfg, route, args, n, dt, logger, reason)
            return code
        return _report(out, cfg, route, args, n, dt, summaries, logger,
                       time.monotonic() - t_start, spec, logs)
    except KeyboardInterrupt:     # (Ctrl-C once the nodes are down: the report is not whole)
        say(f"interrupted while writing the report: the report and the log copies in {out} "
            "are incomplete (bus.log was flushed)")
        return code or EXIT_INTERRUPTED


HUB_SECRET_FILE = "hub.secret"


def _count_tester(args, logger) -> None:
    """A tester's DIAG_REQUEST frames are on the bus but no node sent them: the bus check
    counts them as an outside sender's (on a hub only an authenticated TESTER can send them)."""
    n = logger.log.by_id.get(ID["DIAG_REQUEST"], 0)
    if n:
        args.outside_frames = {**(getattr(args, "outside_frames", None) or {}),
                               "DIAG_REQUEST": n}


def _key_file(args, out: Path) -> Path:
    """The run's SecOC key file: ``--key-file`` (checked), else a new one, DIR/secoc.key
    (mode 0600; it stays, so the log can be verified afterwards)."""
    from hil.cli import fail, key_or_exit

    if getattr(args, "key_file", None):
        key_or_exit(args.key_file)
        return Path(args.key_file).resolve()
    path = out / secoc.KEY_FILE_NAME
    try:
        secoc.write_key(path)
    except OSError as exc:
        fail(f"--out {out}: cannot write the key file: {exc.strerror or exc}")
    return path.resolve()


def _shut_down(nodes: dict, logger: Optional[Logger], log_bus, hub: Optional[Hub]) -> None:
    """Everything this run started, in bounded time: nodes by PID (SIGTERM, SIGKILL after
    5 s), the logger (the log flushed and closed), the bus connection, the hub."""
    for node in nodes.values():
        node.terminate()                 # all at once, then wait for each
    for node in nodes.values():
        node.stop(5.0)
    if logger is not None:
        logger.stop()
        logger.log.close()
    close_bus(log_bus)
    if hub is not None:
        hub.stop()


def _copies(logger: Optional[Logger], formats: tuple, start_us: int, say
            ) -> Optional[list[str]]:
    """The bus log in the other formats asked for (``--log-format``), also after a failed
    run: the names of the logs written, None when a conversion failed (said on stderr)."""
    if logger is None:
        return []
    try:
        return [logger.log.path.name] + [
            p.name for p in convert(logger.log.path, formats, start_us)]
    except Exception as exc:  # noqa: BLE001 - a writer's own error, said in one line
        say(f"run failed: the bus log could not be converted: {type(exc).__name__}: {exc}")
        return None


def _report(out: Path, cfg, route, args, n: int, dt: float, summaries: dict, logger: Logger,
            wall: float, spec: BusSpec, logs: list[str]) -> int:
    from hil.report.figures import write_outputs
    from hil.report.render import finish, render_sil

    report, trace = _build(out, cfg, route, args, dt, summaries)
    report["bench"] = {"harness": "hil", "pace": args.pace, "bus": spec.interface,
                       "frames_logged": logger.log.count, "logs": logs, "wall_s": wall,
                       "rtf": trace.segment.size * dt / wall}
    if logger.kernel_drops is not None:         # socketcan: the logger's own socket
        report["bench"].update(logger_kernel_drops=logger.kernel_drops,
                               logger_rcvbuf_bytes=logger.bus.rcvbuf)
    if args.pace == "realtime":
        report["bench"]["realtime"] = {k: summaries["plant"][k] for k in (
            "missed_deadlines", "missed_deadline_ratio", "lag_p50_us", "lag_p99_us",
            "lag_max_us", "overruns", "cmd_rtt_p50_us", "cmd_rtt_p99_us", "cmd_rtt_max_us",
            "sched")
            if k in summaries["plant"]}
    verdict.attach(report, run_checks(report, summaries, logger.log.by_id, n, dt, args,
                                      sil.fault_ticks(trace)))
    write_outputs(out, report, trace, cfg, route)
    if getattr(args, "junit", None):
        verdict.write_junit(args.junit, _suite(route, args),
                            [verdict.Check(**c) for c in report["checks"]], wall)
    finish(report, None, "report.json", args.json, render_sil)
    if not args.json:
        print(f"report: {out / 'report.md'} (and report.json, bus.log, figures)")
    return verdict.exit_code(report)


def _suite(route, args) -> str:
    """The JUnit suite name of a bench run."""
    return f"hil run {route.name} {args.mode} {args.pace}"


def _build(out: Path, cfg, route, args, dt: float, summaries: dict):
    plant_tr = dict(np.load(out / "plant.npz"))
    ecu_tr = dict(np.load(out / "ecu.npz"))
    trace = sil.merge_traces(dt, plant_tr, ecu_tr)
    report = sil.build_report(cfg, route, args.mode, args.controller, args.seed, trace,
                              summaries["plant"], summaries["ecu"], summaries["app"])
    return report, trace


def _partial_report(out: Path, cfg, route, args, n: int, dt: float, logger: Optional[Logger],
                    reason: Optional[str]) -> None:
    """A run that did not finish still leaves ``report.json`` and ``report.md``: what the
    nodes recorded up to their stop (when they could write it), marked ``incomplete`` with
    the reason, verdict ``fail``. Never raises."""
    from hil.report.figures import markdown
    from hil.report.render import write_json

    reason = reason or "the run did not finish"
    try:
        summaries = {name: json.loads((out / f"{name}.json").read_text()) for name in NODES}
        report, _ = _build(out, cfg, route, args, dt, summaries)
    except Exception as exc:  # noqa: BLE001 - a node died before it wrote its record
        report = {"route": route.name, "mode": args.mode, "controller": args.controller,
                  "seed": args.seed, "vehicle": cfg.source, "duration_s": 0.0, "segments": [],
                  "grade_accuracy": float("nan"), "mode_switches": 0, "grade_changes": 0,
                  "road_holding_entries": 0, "settle_s": sil.SETTLE_S, "trace_sha256": "",
                  "energy": {},
                  "driver": {"policy": args.driver, "requests": {}}, "frames_sent": {},
                  "records": f"not all node records were written ({type(exc).__name__})"}
    report["incomplete"] = reason
    report["bench"] = {"harness": "hil", "pace": args.pace,
                       "frames_logged": logger.log.count if logger else 0}
    checks = [verdict.check("complete", 0, "==", 1),
              verdict.check("span_s", report["duration_s"], "==", n * dt)]
    verdict.attach(report, checks)
    try:
        from hil.cli import _clean

        write_json(_clean(report), out, "report.json")
        (out / "report.md").write_text(markdown(report, []))
    except Exception as exc:  # noqa: BLE001 - the reason was already said; say this too
        print(f"run failed: could not write the partial report: {exc}", file=sys.stderr)
    if getattr(args, "junit", None):
        verdict.write_junit(args.junit, _suite(route, args),
                            [verdict.Check(**c) for c in report["checks"]])
    if args.json:
        from hil.cli import emit

        emit(report, True, lambda _: None)


def run_checks(report: dict, summaries: dict, logged_by_id: dict, n: int, dt: float,
               args, fault_ticks: int) -> list:
    """The verdict's checks of a bench run (``hil.report.verdict.run_checks``) from the nodes'
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
        limits=verdict.limits_of(args), outside_frames=getattr(args, "outside_frames", None))


def _stopped(pid: int) -> bool:
    """The process is stopped (SIGSTOP, a debugger): state T or t in /proc."""
    return _proc_stat(pid)[:1] in (["T"], ["t"])


def _status_faults(view: dict) -> int:
    """The fault word of the last ECU_STATUS in the logger's view."""
    return fault_word({k.split(".", 1)[1]: x for k, x in view.items()
                       if k.startswith("ECU_STATUS.")})


def _line(logger: Logger, dt: float) -> str:
    """The progress line's detail without a terminal: time, grade, modes, faults."""
    v = logger.view
    word = _status_faults(v)
    grade = v.get("ECU_STATUS.ESTIMATED_GRADE")
    rec, act = v.get("MODE_RECOMMEND.RECOMMENDED_MODE"), v.get("ECU_STATUS.ACTIVE_MODE")
    return (f"t = {logger.ticks * dt:.1f} s, grade {name_of(GRADE_NAMES, grade, '?')}, "
            f"recommended {name_of(MODE_NAMES, rec, '-')}, active {name_of(MODE_NAMES, act, '-')}"
            + (f", faults {', '.join(safety.fault_names(word))}" if word else ""))


def _watch(nodes: dict, hub: Optional[Hub], logger: Logger, n: int, dt: float, route,
           args) -> None:
    """Until the plant is done: a live view; stop at the first node that dies, and at the
    first that makes no progress for ``--stall-s`` (named: a stopped process first, else
    the node whose turn it was)."""
    stall_s = getattr(args, "stall_s", None) or STALL_S
    live = None
    if not args.json and sys.stderr.isatty():
        from rich.console import Console
        from rich.live import Live

        live = Live(_view(logger, n, dt, route, args.mode, args.pace),
                    console=Console(stderr=True), refresh_per_second=4, transient=False)
        live.start()
    lines = None
    if live is None and not args.json:
        from hil.cli import progress_lines

        lines = progress_lines(f"run {route.name}", lambda: _line(logger, dt))
    logger.since = time.monotonic()
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
            procs = {name: node.proc.pid for name, node in nodes.items()}
            if hub is not None and hub.proc is not None:
                procs["hub"] = hub.proc.pid
            if plant_rc is not None:
                if plant_rc != 0:
                    held = [name for name, pid in procs.items() if _stopped(pid)]
                    raise NodeFailure(f"node plant exited with code {plant_rc} at t = "
                                      f"{logger.ticks * dt:.2f} s: "
                                      f"{nodes['plant'].last_error()}"
                                      + (f" ({', '.join(held)} stopped)" if held else ""))
                return
            stuck = logger.stalled(time.monotonic(), stall_s, args.pace == "realtime")
            if stuck is not None:
                held = [name for name, pid in procs.items() if _stopped(pid)]
                who = held[0] if held else stuck
                raise NodeFailure(f"{'the hub' if who == 'hub' else 'node ' + who} made no "
                                  f"progress for {stall_s:g} s"
                                  f"{' (the process is stopped)' if held else ''} at t = "
                                  f"{logger.ticks * dt:.2f} s")
            if live is not None:
                live.update(_view(logger, n, dt, route, args.mode, args.pace))
            elif lines is not None:
                lines(logger.ticks, n)
            time.sleep(0.1)
    finally:
        if live is not None:
            live.update(_view(logger, n, dt, route, args.mode, args.pace))
            live.stop()
