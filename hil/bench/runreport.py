"""The end of a bench run: the log's copies in other formats, the report with its verdict,
and a partial report when the run did not finish."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np

from hil.bench.buswatch import Logger
from hil.bench.spec import RunSpec
from hil.nodes import sil
from hil.nodes import message_name
from hil.report import verdict
from hil.transport.bus import BusSpec
from hil.transport.buslog import convert


NODES = ("ecu", "app", "plant")


def log_copies(logger: Optional[Logger], formats: tuple, start_us: int, say
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


def write_report(out: Path, cfg, route, args: RunSpec, n: int, dt: float, summaries: dict,
                 logger: Logger, wall: float, spec: BusSpec, logs: list[str],
                 judge=None) -> int:
    """The report of a finished run with its verdict; ``judge(report, cfg, route, args)``
    adds the checks of a layer above the bench (``hil run``'s ride: hil.validate.ride)."""
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
    if judge is not None and not args.inject:   # (a run with faults: the fault campaign's)
        judge(report, cfg, route, args)
    write_outputs(out, report, trace, cfg, route)
    if args.junit:
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
    if args.calibration:
        report["calibration"] = args.calibration
    return report, trace


def partial_report(out: Path, cfg, route, args: RunSpec, n: int, dt: float, logger: Optional[Logger],
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
    if args.junit:
        verdict.write_junit(args.junit, _suite(route, args),
                            [verdict.Check(**c) for c in report["checks"]], None)
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
        pace=args.pace, injected=bool(args.inject),
        lost_sensor_frames=lost, missed_deadlines=plant.get("missed_deadlines", 0),
        fault_ticks=fault_ticks,
        limits=verdict.limits_of(args), outside_frames=args.outside_frames)
