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

import dataclasses
import json
import os
import secrets
import signal
import sys
import time
from pathlib import Path
from typing import Optional


from hil.bench.buswatch import Logger, live_view, progress_line
from hil.bench.nodeproc import (EXIT_INTERRUPTED, EXIT_NODE, Interrupted, Node, NodeFailure,
                               on_signals, stopped)
from hil.bench.runreport import NODES, log_copies, partial_report, write_report
from hil.bench.spec import RunSpec
from hil.nodes import sil
from hil.nodes import ID
from hil.transport import secoc
from hil.transport.auth import SECRET_ENV
from hil.transport.bus import (RT_PRIORITY, BusError, BusSpec, Hub, SocketcanTap, close_bus,
                               resolve, rt_of)
from hil.transport.buslog import HUB_CHANNEL, BusLogFile, copies_of
from hil.transport.codec import Codec

STALL_S = 20.0               # no progress for this long stops the run (--stall-s)


def _check_inputs(args: RunSpec):
    from hil.cli import cars_or_exit, design_or_exit, fail, route_or_exit
    from hil.config import ConfigError, load_driver_script

    cfg, cal = cars_or_exit(args.vehicle, args.calibration)
    route = route_or_exit(args.route)
    design_or_exit(args.design)          # (checked here; the ECU node reads it)
    try:
        sil.check_route(cfg, route)
        if args.script:
            load_driver_script(args.script)
        if args.gains:
            from calib.control_design import load_gains

            load_gains(Path(args.gains), cal)
    except ConfigError as exc:
        fail(str(exc))
    if args.driver == "script" and not args.script:
        fail("run: --driver script needs --script FILE")
    if args.driver == "interactive":
        fail("run: --driver interactive needs the app's own terminal, which the bench's nodes "
             "do not have: use --driver web (a page on 127.0.0.1), or start python -m hil app "
             "--policy interactive beside the nodes")
    return cfg, route


def _node_argvs(args: RunSpec, spec: BusSpec, out: Path, rt: int, key_file: Path,
                n: Optional[int] = None) -> dict[str, list[str]]:
    common = ["-i", spec.interface, "-c", spec.channel, "--out", str(out), "--pace", args.pace,
              "--key-file", str(key_file)]
    car = ["--vehicle", args.vehicle] if args.vehicle else []
    # the ECU's car is the one it is calibrated for; the plant drives --vehicle at that
    # car's ride height
    ecu = [*common, *(["--vehicle", args.calibration] if args.calibration else car),
           "--mode", args.mode, "--rt-priority", str(rt_of(rt, "ecu"))]
    common += car
    for flag, value in (("--controller", args.controller), ("--gains", args.gains),
                        ("--design", args.design)):
        if value:
            ecu += [flag, value]
    if args.fixed_point:
        ecu += ["--fixed-point"]
    if n is not None:             # (the drive's samples: after the last, no timeout)
        ecu += ["--ticks", str(n)]
    app = [*common, "--mode", args.mode, "--quiet", "--rt-priority", str(rt_of(rt, "app"))]
    if args.driver:
        app += ["--policy", args.driver]
    if args.driver == "web":
        app += ["--web-port", str(args.web_port or 0)]
    if args.script:
        app += ["--script", args.script]
    plant = [*common, "--route", args.route, "--seed", str(args.seed),
             "--rt-priority", str(rt_of(rt, "plant"))]
    if args.calibration:
        plant += ["--calibration", args.calibration]
    if args.inject:       # hil faults: the injector's plan
        plant += ["--inject", args.inject]
        app += ["--inject", args.inject]
    if args.duration is not None:
        plant += ["--duration", repr(args.duration)]
    return {"ecu": ecu, "app": app, "plant": plant}


def run(args: RunSpec, on_bus=None, judge=None) -> int:
    """The run ``args`` specifies. ``on_bus(spec)``: called once the bus is up, before the
    nodes start (the fault campaign attaches its outside clients there); ``judge``: more
    checks of the finished run's report (``runreport.write_report``)."""
    from hil.cli import lock_out, log_options_or_exit

    cfg, route = _check_inputs(args)
    if args.pace is None:            # a person at the page drives at the car's pace
        args = dataclasses.replace(args, pace="realtime" if args.driver == "web" else "lockstep")
    start_us, formats = log_options_or_exit(args)
    t0 = time.monotonic()                # (the moment of start_us, on the monotonic clock)
    out = lock_out(args.out)
    _clear_outputs(out)
    key_file = _key_file(args, out)
    dt = cfg.sim.plant_dt_s
    n = int(round(route.duration_s / dt))
    if args.duration is not None:
        n = min(n, int(round(args.duration / dt)))
    s = _Session(args, out, dt)
    s.n = n
    code, reason, summaries = 0, None, None
    t_start = time.monotonic()
    previous = on_signals()
    try:
        s.start_bus(start_us, t0, on_bus)
        s.start_nodes(key_file)
        _watch(s.nodes, s.hub, s.logger, n, dt, route, args)
        summaries = s.stop_nodes()
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
        what = "" if signum == signal.SIGINT else f" ({signal.Signals(signum).name})"
        reason = f"interrupted{what} at t = {s.logger.ticks * dt if s.logger else 0.0:.2f} s"
        _say(f"{reason}; nodes stopped, {out / 'bus.log'} flushed")
        code = EXIT_INTERRUPTED if signum == signal.SIGINT else 128 + signum
    except (NodeFailure, BusError) as exc:
        reason = str(exc)
        _say(f"run failed: {exc}")
        code = EXIT_NODE if isinstance(exc, NodeFailure) else 3
    finally:
        _shut_down(s.nodes, s.logger, s.log_bus, s.hub)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    try:
        logs = log_copies(s.logger, formats, start_us, _say)
        if logs is None and not code:
            code, reason = EXIT_NODE, "the bus log could not be converted"
        if code:
            partial_report(out, cfg, route, args, n, dt, s.logger, reason)
            return code
        return write_report(out, cfg, route, args, n, dt, summaries, s.logger,
                            time.monotonic() - t_start, s.spec, logs, judge)
    except KeyboardInterrupt:     # (Ctrl-C once the nodes are down: the report is not whole)
        _say(f"interrupted while writing the report: the report and the log copies in {out} "
             "are incomplete (bus.log was flushed)")
        return code or EXIT_INTERRUPTED


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _clear_outputs(out: Path) -> None:
    """A run leaves no earlier run's outputs behind (a failed run no old report)."""
    from hil.report.figures import FIGURES

    stale = [f"{n}{x}" for n in NODES for x in (".json", ".npz", ".log")]
    copies = [p.name for p in copies_of(out / "bus.log")]
    for name in (*stale, *copies, "app.url", "hub.log", "report.json", "report.md",
                 secoc.KEY_FILE_NAME, HUB_SECRET_FILE, *FIGURES):
        (out / name).unlink(missing_ok=True)


class _Session:
    """What one run starts, in order (the bus with its hub and logger, the nodes), and what
    ``_shut_down`` stops whatever happened."""

    def __init__(self, args: RunSpec, out: Path, dt: float):
        self.args, self.out, self.dt = args, out, dt
        self.n: Optional[int] = None       # the drive's ticks (the ECU's last sample)
        self.hub: Optional[Hub] = None
        self.nodes: dict[str, Node] = {}
        self.logger: Optional[Logger] = None
        self.log_bus = None
        self.spec: Optional[BusSpec] = None
        self.rt = args.rt_priority
        if self.rt is None:
            self.rt = RT_PRIORITY if args.pace == "realtime" else 0
        self.env = {k: v for k, v in os.environ.items() if k != SECRET_ENV}

    def start_bus(self, start_us: int, t0: float, on_bus) -> None:
        args, out = self.args, self.out
        spec, needs_hub = resolve(args.interface, args.channel)
        if needs_hub:
            # the run's secret: to the hub and the nodes in their environment, never argv
            self.env[SECRET_ENV] = secrets.token_hex(16)
            # (for a tester, hil diag --secret-file: a key file, mode 0600, never argv)
            secoc.write_key(out / HUB_SECRET_FILE, bytes.fromhex(self.env[SECRET_ENV]))
            self.hub = Hub(rt_priority=rt_of(self.rt, "hub"), secret=self.env[SECRET_ENV],
                           allow_external_tx=args.allow_external_tx,
                           allow_unknown_ids=bool(args.inject),
                           log_path=out / "hub.log").start()
            spec = BusSpec("remote", self.hub.url)
        assert spec is not None
        self.spec = spec
        _say(f"bus: {spec.interface} {spec.channel}  (watch: python -m can.viewer -i "
             f"{spec.interface} -c {spec.channel})")
        self.log_bus = (SocketcanTap(spec.channel) if spec.interface == "socketcan"
                        else spec.open())
        channel = spec.channel if spec.interface == "socketcan" else HUB_CHANNEL
        self.logger = Logger(self.log_bus, BusLogFile(out / "bus.log", channel, start_us),
                             args.pace == "lockstep", self.dt, Codec(), t0)
        self.logger.start()
        if on_bus is not None:
            on_bus(spec)

    def start_nodes(self, key_file: Path) -> None:
        """The ECU and the app, then (both READY) the plant, which owns simulated time."""
        argvs = _node_argvs(self.args, self.spec, self.out, self.rt, key_file, self.n)
        for name in ("ecu", "app"):
            self.nodes[name] = Node(name, argvs[name], self.out, self.env)
        for name in ("ecu", "app"):
            self.nodes[name].wait_ready()
        if self.args.driver == "web":
            _say(f"driver page: {(self.out / 'app.url').read_text().strip()}  (the driver "
                 "app: accept, refuse or choose a mode there)")
        self.nodes["plant"] = Node("plant", argvs["plant"], self.out, self.env)
        self.nodes["plant"].wait_ready()

    def stop_nodes(self) -> dict:
        """The plant is done: the ECU and the app stopped, their records read; the log must
        hold every frame they (and any outside client) report sending."""
        for name in ("ecu", "app"):
            rc = self.nodes[name].stop()
            if rc not in (0, None):
                raise NodeFailure(f"node {name} exited with code {rc}: "
                                  f"{self.nodes[name].last_error()}")
        summaries = {name: json.loads((self.out / f"{name}.json").read_text())
                     for name in NODES}
        _count_tester(self.args, self.logger)
        sent = sum(sum(s["frames_sent"].values()) for s in summaries.values()) + sum(
            self.args.outside_frames.values())
        if not self.logger.wait_for(sent, 10.0):
            raise NodeFailure(f"bus.log holds {self.logger.log.count} frames, the nodes sent "
                              f"{sent}" + self.logger.drops_said())
        return summaries


HUB_SECRET_FILE = "hub.secret"


def _count_tester(args: RunSpec, logger) -> None:
    """A tester's DIAG_REQUEST and XCP_CMD frames are on the bus but no node sent them: the
    bus check counts them as an outside sender's (on a hub only an authenticated TESTER can
    send them)."""
    for name in ("DIAG_REQUEST", "XCP_CMD"):
        n = logger.log.by_id.get(ID[name], 0)
        if n:
            args.outside_frames = {**args.outside_frames, name: n}


def _key_file(args: RunSpec, out: Path) -> Path:
    """The run's SecOC key file: ``--key-file`` (checked), else a new one, DIR/secoc.key
    (mode 0600; it stays, so the log can be verified afterwards)."""
    from hil.cli import fail, key_or_exit

    if args.key_file:
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


def _watch(nodes: dict, hub: Optional[Hub], logger: Logger, n: int, dt: float, route,
           args: RunSpec) -> None:
    """Until the plant is done: a live view; stop at the first node that dies, and at the
    first that makes no progress for ``--stall-s`` (named: a stopped process first, else
    the node whose turn it was)."""
    stall_s = args.stall_s or STALL_S
    live = None
    if not args.json and sys.stderr.isatty():
        from rich.console import Console
        from rich.live import Live

        live = Live(live_view(logger, n, dt, route, args.mode, args.pace),
                    console=Console(stderr=True), refresh_per_second=4, transient=False)
        live.start()
    lines = None
    if live is None and not args.json:
        from hil.cli import progress_lines

        lines = progress_lines(f"run {route.name}", lambda: progress_line(logger, dt))
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
                    held = [name for name, pid in procs.items() if stopped(pid)]
                    raise NodeFailure(f"node plant exited with code {plant_rc} at t = "
                                      f"{logger.ticks * dt:.2f} s: "
                                      f"{nodes['plant'].last_error()}"
                                      + (f" ({', '.join(held)} stopped)" if held else ""))
                return
            stuck = logger.stalled(time.monotonic(), stall_s, args.pace == "realtime")
            if stuck is not None:
                held = [name for name, pid in procs.items() if stopped(pid)]
                who = held[0] if held else stuck
                raise NodeFailure(f"{'the hub' if who == 'hub' else 'node ' + who} made no "
                                  f"progress for {stall_s:g} s"
                                  f"{' (the process is stopped)' if held else ''} at t = "
                                  f"{logger.ticks * dt:.2f} s")
            if live is not None:
                live.update(live_view(logger, n, dt, route, args.mode, args.pace))
            elif lines is not None:
                lines(logger.ticks, n)
            time.sleep(0.1)
    finally:
        if live is not None:
            live.update(live_view(logger, n, dt, route, args.mode, args.pace))
            live.stop()
