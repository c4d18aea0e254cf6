"""The reliability campaign: ``python -m hil faults [--json]``.

The faults are the families of ``hil.faults`` (one plug-in each, in ``hil.faults.registry``);
their injector sits in the transmit and receive path of the plant and the driver-app nodes (a
faulty transceiver, a broken sensor, a babbling sender, a careless app) and changes what they
put on the bus, on a fixed schedule of tick windows; the campaign's outside clients (an
attacker and a UDS tester) act on the bus itself. One lockstep run over the bus (hub or
vcan0) drives the ECU through every bus fault in turn, separated by fault-free gaps; the
configuration faults are separate ECU starts with a broken file. Each fault is then judged from
the ECU's per-tick record (fault word, bridge enable), the plant's (passive fallback) and what
the driver app received (ECU_STATUS FAULTS/REASON):

* ``detected``: the fault's bit is set in the ECU's fault word (actuator-command loss: the plant
  fell back to passive; a broken configuration file: a one-line error, exit code 2); None for
  a fault the ECU is meant to ride through (a one-sample glitch), whose family judges that;
* ``reaction_ticks``: ticks from the first faulty tick to the fail-safe state (bridge disabled,
  no active force) for a safety-relevant fault, to the fault bit otherwise;
* ``recovered``: after the fault, the ECU is back to a clean fault word with the bridge enabled
  before the next fault; ``recovery_ticks`` counts from the last faulty tick (the hysteresis:
  at least the ADC's run of good samples for a sensor fault);
* ``crashed``: a node died or printed a traceback;
* ``driver_told``: the app received an ECU_STATUS naming the fault.

Everything is deterministic: the same seed gives the same campaign over the hub and in one
process (``--in-process``), tick for tick.
"""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np

from firmware import params as fp
from hil.faults.base import (CAMPAIGN_GRADE, CAMPAIGN_MODE, CAMPAIGN_SPEED_MPS,
                             MAX_ACTUATOR_TICKS, MAX_PLAUSIBLE_TICKS, MAX_REACTION_TICKS,
                             Evidence, Result, Window)
from hil.faults.injector import Injector
from hil.faults.registry import BY_NAME, FAULTS, campaign_ticks, schedule
from hil.nodes import ID


# -- judging ----------------------------------------------------------------------------------

def judge(windows: list[Window], ecu_tr: dict, plant_tr: dict, applied: dict,
          faults_seen: list, ticks_run: int, crash: Optional[str], mode: int,
          hub_log: str = "", dtcs: Optional[dict] = None) -> list[Result]:
    """Per bus fault: its family judges the ECU's and the plant's per-tick records around its
    window (and the hub's log, for an outside client's frames; the DTCs read after it)."""
    faults = np.asarray(ecu_tr["faults"], dtype=np.int64)
    enable = np.asarray(ecu_tr["enable"], dtype=bool)
    modes = np.asarray(ecu_tr["mode"])
    degraded = np.asarray(ecu_tr["degraded"])
    fallback = np.asarray(plant_tr["fallback"], dtype=bool)
    n = min(len(faults), len(fallback))
    out = []
    for i, w in enumerate(windows):
        spec = BY_NAME[w.name]
        end = windows[i + 1].start if i + 1 < len(windows) else n
        crashed = crash is not None and ticks_run < end
        a = applied.get(w.name)
        if a is None or a[0] >= n:
            out.append(Result(w.name, False, None, False, crashed, spec.safety,
                              note="not injected" if a is None else "run ended first"))
            continue
        out.append(spec.judge(Evidence(w, a, end, faults, enable, modes, fallback, plant_tr,
                                       faults_seen, crashed, mode, hub_log,
                                       (dtcs or {}).get(w.name), degraded)))
    return out


def config_faults(out: Path, names: Optional[list[str]] = None) -> list[Result]:
    """The configuration faults: each an ECU start with a broken file."""
    out.mkdir(parents=True, exist_ok=True)
    return [f.run(out) for f in FAULTS
            if f.node == "config" and (names is None or f.name in names)]


# -- the outside clients ----------------------------------------------------------------------

# what the outside clients count the plant's ticks by: one of these frames per tick
_TICK_FRAMES = [{"can_id": ID[n], "can_mask": 0x7FF, "extended": False}
                for n in ("PLANT_SENSORS", "SIM_TICK")]


def _attacker(windows: list[Window], spec, marks: dict, stop, on_bus: dict) -> None:
    """The campaign's outside bus client: read-only (no credentials), it counts the plant's
    ticks from the bus and, in its windows, sends a forged ACTUATOR_CMD with every tick
    (``external_sender``) or a malformed message to the hub (``hub_message``): the family's
    ``act``. ``on_bus`` counts the frames it put on the bus itself (vcan0: no hub drops
    them), so the run's check of frames on the bus against frames sent counts them too."""
    from hil.transport.codec import Codec

    codec = Codec()
    mine = [w for w in windows if w.node == "bus"]
    if spec.interface != "remote":
        mine = [w for w in mine if not BY_NAME[w.name].needs_hub]
    if not mine:
        return
    bus = spec.open(can_filters=_TICK_FRAMES)
    k = -1                  # the plant's tick of the last tick frame seen (the first is tick 0)
    try:
        while not stop.is_set() and mine:
            msg = bus.recv(0.2)
            if msg is None:
                continue
            k += 1
            w = mine[0]
            if k < w.start:
                continue
            if k >= w.start + w.ticks:
                mine.pop(0)
                continue
            a = marks.setdefault(w.name, [k, k, 0])
            a[1], a[2] = k, a[2] + 1
            if not BY_NAME[w.name].act(bus, spec, k, codec, on_bus):
                mine.pop(0)
    finally:
        from hil.transport.bus import close_bus

        close_bus(bus)


# ticks after a plausible fault's window: its DTCs are read (the isolation bank decides once
# the evidence ended: the tests and its filters quiet for fdi_settle_s; 300 ms windows)
DTC_READ_AFTER = 3000
DTC_CLEAR_BEFORE = 300          # ... and before the first one, the DTCs of the earlier faults
#                                 are cleared (so each snapshot is the fault's own)


def _read_points(windows: list[Window]) -> list[tuple[int, Optional[Window]]]:
    """(tick, window) of the tester's reads, each followed by a clear; window None: a clear
    before the first plausible fault."""
    points = [(w.start + w.ticks + DTC_READ_AFTER, w) for w in windows
              if BY_NAME[w.name].plausible]
    if points:
        first = next(w for w in windows if BY_NAME[w.name].plausible)
        points.insert(0, (max(0, first.start - DTC_CLEAR_BEFORE), None))
    return points


def _tester(windows: list[Window], spec, out: Path, reads: dict, stop) -> None:
    """The campaign's UDS tester: udsoncan over can-isotp, as ``python -m hil diag`` (on a hub
    authenticated as TESTER with the run's hub.secret). It counts the plant's ticks from the
    bus; ``DTC_READ_AFTER`` ticks after each plausible fault's window it reads the DTCs
    (status, snapshot, extended data) and clears them, and says so when the read was not
    over before the next fault began; ``DTC_CLEAR_BEFORE`` ticks before the first one it
    only clears (one exchange: reading the earlier faults' DTCs first took longer than those
    ticks on vcan0 in UML, and the late clear wiped the first fault's own)."""
    points = _read_points(windows)
    if not points:
        return
    from hil.apps import diag
    from hil.transport.bus import close_bus
    from hil.transport.secoc import load_key

    ticks = bus = None
    try:
        ticks = spec.open(can_filters=_TICK_FRAMES)
        bus = diag.tester_bus(spec, load_key(out / "hub.secret")
                              if spec.interface == "remote" else None)
        with diag.client(bus, timeout=2.0) as client:
            k = -1
            late_clear: dict = {}      # fault -> the tick the clear before it ended, late
            while not stop.is_set() and points:
                msg = ticks.recv(0.2)
                if msg is None:
                    continue
                k += 1
                if k == 0:
                    # the first exchange sets up both ISO-TP stacks (the ECU node imports
                    # its own on the first request): here, long before the first read, not
                    # in a read's time (on vcan0 in UML it took longer than the 300 ticks
                    # between the first clear and the fault after it)
                    try:
                        client.tester_present()
                    except Exception:  # noqa: BLE001 - the reads below say what fails
                        pass
                    while ticks.recv(0) is not None:
                        k += 1
                    continue
                at, w = points[0]
                if k < at:
                    continue
                points.pop(0)
                try:
                    if w is None:       # (the clear before the first fault: one exchange)
                        client.clear_dtc(0xFFFFFF)
                        doc = {"dtcs": [], "cleared": True}
                    else:
                        doc = diag.read_dtcs(client, clear=True)
                except Exception as exc:  # noqa: BLE001 - a failed read is a finding
                    doc = {"error": f"UDS read failed: {type(exc).__name__}: {exc}"}
                while ticks.recv(0) is not None:       # the ticks that passed meanwhile
                    k += 1
                later = [x for x in windows if x.start >= at]
                if later and k >= later[0].start and "error" not in doc:
                    doc = {"error": f"the read ended at tick {k}, after the next fault began"}
                    if w is None:          # a late clear may have wiped the next fault's DTCs
                        late_clear[later[0].name] = k
                if w is not None and w.name in late_clear and "error" not in doc:
                    doc = {"error": f"the clear before this fault ended at tick "
                                    f"{late_clear[w.name]}, after it began"}
                reads[w.name if w else "(clear)"] = doc
    except Exception as exc:  # noqa: BLE001 - the tester could not work: every read says so
        for _, w in points:
            reads.setdefault(w.name if w else "(clear)",
                             {"error": f"the UDS tester failed: {type(exc).__name__}: {exc}"})
    finally:
        for b in (ticks, bus):
            if b is not None:
                close_bus(b)


def _read_memory(node) -> dict:
    """In process (no bus): the DTCs straight from the ECU's memory, as the tester reports
    them, then cleared (``--in-process`` only; the bus campaign reads them over UDS)."""
    from firmware.diag import dtc as fw
    from hil.apps.diag import dtc_label

    out = []
    for i, e in enumerate(node.state.diag.dtc.entries):
        if e.status & 0x2F:
            d = fw.DTCS[i]
            snap = e.snapshot
            out.append({"code": dtc_label(d.code), "name": d.name, "status": e.status,
                        **({"snapshot": {"tick": snap.tick, "speed_mps": None
                                         if snap.speed_cmps == 0xFFFF else snap.speed_cmps / 100}}
                           if snap else {})})
    node.state.diag.clear(0xFFFFFF)
    return {"dtcs": out}


# -- running ----------------------------------------------------------------------------------

def _route_file(out: Path, ticks: int, dt: float) -> Path:
    length = CAMPAIGN_SPEED_MPS * (ticks * dt + 1.0)
    path = out / "route.toml"
    path.write_text(f'name = "faults"\ndescription = "fault campaign: grade {CAMPAIGN_GRADE} '
                    f'at {CAMPAIGN_SPEED_MPS:g} m/s"\n\n[[segment]]\ngrade = "{CAMPAIGN_GRADE}"\n'
                    f"length_m = {length:.1f}\nspeed_mps = {CAMPAIGN_SPEED_MPS:g}\n")
    return path


def run_in_process(windows: list[Window], out: Path, seed: int = 1,
                   compiled: bool = True) -> dict:
    """The campaign with the three nodes in this process (the lockstep FIFO): the compiled
    SIL loop between the windows (``hil.nodes.fastsil``; the node objects in them and at the
    tester's reads), or (``compiled=False``) the node objects throughout."""
    from hil.nodes import fastsil
    from hil import nodes
    from hil.transport import secoc
    from hil.transport.codec import Codec
    from hil.config import default_vehicle
    from hil.sim.road import load_route
    from hil.nodes.sil import app_node, ecu_params

    cfg = default_vehicle()
    dt = cfg.sim.plant_dt_s
    n = campaign_ticks(windows)
    route = load_route(_route_file(out, n, dt))
    codec = Codec()
    key = secoc.new_key()
    plant = nodes.PlantNode(cfg, route, seed, codec, inject=Injector(windows, "plant"),
                            key=key)
    plant.n = min(plant.n, n)
    ecu_node = nodes.EcuNode(ecu_params(cfg, CAMPAIGN_MODE), codec, key=key)
    app = app_node(codec, CAMPAIGN_MODE, dt, key=key)
    app.inject = Injector(windows, "app")
    points, reads, tick = _read_points(windows), {}, ecu_node.tick

    def ticking():
        while points and ecu_node.k >= points[0][0]:
            w = points.pop(0)[1]
            reads[w.name if w else "(clear)"] = _read_memory(ecu_node)
        return tick()

    ecu_node.tick = ticking
    crash = None
    try:
        if compiled:
            fastsil.run(plant, ecu_node, app, python=[(k, k + 1) for k, _ in points])
        else:
            nodes.run_in_process(plant, ecu_node, app)
    except Exception as exc:  # noqa: BLE001 - a crash is a finding, reported per fault
        crash = f"{type(exc).__name__}: {exc}"
    return {"ecu": ecu_node.trace(), "plant": plant.trace(),
            "applied": {**plant.inject.applied, **app.inject.applied},
            "faults_seen": app.faults_seen, "ticks": ecu_node.k, "crash": crash,
            "dtcs": reads, "summaries": [node.summary() for node in (plant, ecu_node, app)]}


def run_over_bus(windows: list[Window], out: Path, seed: int = 1,
                 interface: Optional[str] = None, channel: Optional[str] = None) -> dict:
    """The campaign as ``hil run --pace lockstep`` with the injector in the plant and app
    processes (``--inject``); a node that dies or prints a traceback is a crash."""
    from hil.bench import supervisor
    from hil.bench.spec import RunSpec
    from hil.config import default_vehicle

    dt = default_vehicle().sim.plant_dt_s
    n = campaign_ticks(windows)
    plan = out / "plan.json"
    plan.write_text(json.dumps({"windows": [asdict(w) for w in windows]}, indent=1) + "\n")
    args = RunSpec(route=str(_route_file(out, n, dt)), mode=CAMPAIGN_MODE, seed=seed,
                   duration=n * dt, out=str(out), pace="lockstep", interface=interface,
                   channel=channel, inject=str(plan))
    marks: dict = {}
    reads: dict = {}
    stop = threading.Event()
    threads: list = []

    def attach(spec):                 # the outside clients, once the bus is up
        for target, extra in ((_attacker, (windows, spec, marks, stop, args.outside_frames)),
                              (_tester, (windows, spec, out, reads, stop))):
            t = threading.Thread(target=target, args=extra, daemon=True)
            t.start()
            threads.append(t)

    with contextlib.redirect_stdout(sys.stderr):
        code = supervisor.run(args, on_bus=attach)
    stop.set()
    for t in threads:
        t.join(5.0)
    crash = None if code == 0 else f"hil run exited with code {code}"
    for name in supervisor.NODES:
        log = out / f"{name}.log"
        if log.exists() and "Traceback" in log.read_text(errors="replace"):
            crash = f"node {name} printed a traceback (see {log})"
    try:
        ecu_tr, plant_tr = dict(np.load(out / "ecu.npz")), dict(np.load(out / "plant.npz"))
        sums = {k: json.loads((out / f"{k}.json").read_text()) for k in ("plant", "app")}
    except (OSError, ValueError) as exc:
        return {"ecu": {"faults": [], "enable": [], "mode": []}, "plant": {"fallback": []},
                "applied": {}, "faults_seen": [], "ticks": 0,
                "crash": crash or f"no node records: {exc}"}
    hub_log = out / "hub.log"
    return {"ecu": ecu_tr, "plant": plant_tr,
            "applied": {**sums["plant"].get("injected", {}), **sums["app"].get("injected", {}),
                        **marks},
            "faults_seen": [tuple(e) for e in sums["app"]["faults_seen"]],
            "ticks": len(ecu_tr["faults"]), "crash": crash, "dtcs": reads,
            "hub_log": hub_log.read_text(errors="replace") if hub_log.exists() else ""}


def campaign(out: Path, *, in_process: bool = False, seed: int = 1,
             names: Optional[list[str]] = None, interface: Optional[str] = None,
             channel: Optional[str] = None) -> list[Result]:
    out.mkdir(parents=True, exist_ok=True)
    windows = schedule(names, bus=not in_process)
    if not in_process and not _on_hub(interface, channel):      # vcan0: no hub to attack
        windows = [w for w in windows if not BY_NAME[w.name].needs_hub]
    results: list[Result] = []
    if windows:
        run = (run_in_process(windows, out, seed) if in_process
               else run_over_bus(windows, out, seed, interface, channel))
        results += judge(windows, run["ecu"], run["plant"], run["applied"],
                         run["faults_seen"], run["ticks"], run["crash"],
                         fp.MODE_COMFORT, run.get("hub_log", ""), run.get("dtcs"))
        if run["crash"]:
            print(f"faults: {run['crash']}", file=sys.stderr, flush=True)
    results += config_faults(out / "config", names)
    return results


def _on_hub(interface: Optional[str], channel: Optional[str]) -> bool:
    from hil.transport.bus import BusError, resolve

    try:
        spec, needs_hub = resolve(interface, channel)
    except BusError:
        return True                   # (the run itself says what is wrong)
    return needs_hub or spec.interface == "remote"


def passed(results: list[Result]) -> bool:
    return all(BY_NAME[r.fault].holds(r) for r in results)


def checks(results: list[Result]) -> list:
    """The verdict's checks: one per fault. Value: the reaction in ticks (or what went wrong);
    limit: what the fault must meet."""
    from hil.report.verdict import Check

    return [Check(f"fault.{r.fault}", BY_NAME[r.fault].value_text(r),
                  BY_NAME[r.fault].limit_text(r), BY_NAME[r.fault].holds(r)) for r in results]


def _table(results: list[Result]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"fault campaign: ECU in {CAMPAIGN_MODE} mode, grade {CAMPAIGN_GRADE} at "
                    f"{CAMPAIGN_SPEED_MPS:g} m/s, lockstep (ticks of 1 ms)")
    for col in ("fault", "safety", "detected", "reaction", "recovered", "recovery", "crashed",
                "driver told", "fault bits", "dtc", "detect_ms", "isolation"):
        t.add_column(col, no_wrap=True)

    def cell(v, bad=False):
        if v is None:
            return "-"
        if isinstance(v, bool):
            return ("yes" if v else "NO") if bad else ("yes" if v else "no")
        return str(v)

    for r in results:
        bits = BY_NAME[r.fault].table_note(r)
        t.add_row(r.fault, cell(r.safety_relevant), cell(r.detected, True),
                  cell(r.reaction_ticks), cell(r.recovered, True), cell(r.recovery_ticks),
                  "YES" if r.crashed else "no", cell(r.driver_told, True), bits,
                  ", ".join(d.split()[0] for d in r.dtc) if r.dtc else "-",
                  cell(r.detect_ms), r.isolation or "-")
    console = Console()
    if not console.is_terminal:
        console = Console(width=200)
    console.print(t)


def main(args) -> int:
    names = None
    if args.only:
        names = [s.strip() for s in args.only.split(",") if s.strip()]
        unknown = sorted(set(names) - set(BY_NAME))
        if unknown:
            from hil.cli import fail

            fail(f"faults: unknown fault(s) {', '.join(unknown)} "
                 f"(known: {', '.join(BY_NAME)})")
    from hil.cli import lock_out

    lock_out(args.out)
    t0 = time.monotonic()
    results = campaign(Path(args.out), in_process=args.in_process, seed=args.seed, names=names,
                       interface=getattr(args, "interface", None),
                       channel=getattr(args, "channel", None))
    from hil.report import verdict

    held = checks(results)
    doc = verdict.attach({"results": [asdict(r) for r in results]}, held)
    (Path(args.out) / "faults.json").write_text(json.dumps(doc, indent=1) + "\n")
    if getattr(args, "junit", None):
        verdict.write_junit(args.junit, "hil faults", held, time.monotonic() - t0)
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        _table(results)
        frame = [r for r in results if r.safety_relevant and not BY_NAME[r.fault].plausible]
        kinds = (("plausible sensor faults", MAX_PLAUSIBLE_TICKS),
                 ("actuator and supply faults", MAX_ACTUATOR_TICKS))
        model = "".join(
            f", {what} {max(r.reaction_ticks or 0 for r in rs)} ticks (limit {limit})"
            for what, limit in kinds
            for rs in [[r for r in results if BY_NAME[r.fault].plausible
                        and BY_NAME[r.fault].limit == limit]] if rs)
        claimed = [r for r in results if r.detected is not None]
        print(f"{sum(r.detected for r in claimed)}/{len(claimed)} detected"
              + (f" ({len(results) - len(claimed)} to ride through)"
                 if len(claimed) < len(results) else "") + ", "
              f"{sum(r.crashed for r in results)} crashed, max safety reaction "
              f"{max((r.reaction_ticks or 0) for r in frame) if frame else 0} ticks "
              f"(limit {MAX_REACTION_TICKS}){model}"
              f"; {time.monotonic() - t0:.1f} s; {Path(args.out) / 'faults.json'}")
        verdict.render(doc)
    return verdict.exit_code(doc)
