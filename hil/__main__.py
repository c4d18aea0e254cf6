"""``python -m hil``: the bench's command line.

    python -m hil run --route full_road_section --mode auto --seed 1 --pace lockstep --out DIR
    python -m hil ecu|plant|app -i remote -c ws://127.0.0.1:PORT/ ...   (one node)
    python -m hil sim --route full_road_section --mode auto --seed 1 [--controller C] [--json]
    python -m hil drive --route full_road_section --seed 1 [--out DIR] [--json]
    python -m hil routes
    python -m hil vcan [-- COMMAND ...]      (User-mode Linux with vcan0 up; hil/transport/vcan.py)
    python -m hil logdiff CANDUMP.log BUS.log [--json]
    python -m hil diag -i remote -c ws://127.0.0.1:PORT/ --secret-file DIR/hub.secret [--clear]
    python -m hil xcp info|get|set|measure -i remote -c ws://... --secret-file DIR/hub.secret
                      --key-file DIR/secoc.key ...                 (hil/apps/xcptool.py)
    python -m hil alarms [--routes R,..] [--seeds N] [--vehicles F,..] [--speeds V,..] [--json]
"""

from __future__ import annotations

import argparse

from hil import parsers
from hil.cli import OneLineParser, apply_cache_argument, route_or_exit, vehicle_or_exit
from hil.report import verdict

# the commands whose options include python-can's bus options: their parsers import can,
# which imports every log format's library (asammdf and pandas: a quarter second); for any
# other command they are not built (unless the command is unknown or help is asked for)
BUS_COMMANDS = ("run", "plant", "ecu", "app", "faults", "diag", "xcp")
OTHER_COMMANDS = ("drive", "routes", "logdiff", "alarms", "keygen", "cache", "campaign",
                  "campaign-case", "campaign-report", "sim")


def main(argv: list[str] | None = None) -> int:
    import sys

    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["vcan"]:        # (its own parser: everything after it may be a command)
        from hil.transport import vcan

        return vcan.main(argv[1:])
    args = _parser(argv).parse_args(argv)
    apply_cache_argument(args)
    return _COMMANDS.get(args.command, _drive)(args)


def _parser(argv: list[str]) -> argparse.ArgumentParser:
    """Every command's parser; the bus commands' only when they can be asked for."""
    parser = OneLineParser(prog="python -m hil", description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    bus_parsers = not (argv[:1] and argv[0] in OTHER_COMMANDS)
    parsers.add_commands(sub, bus_parsers)
    return parser



def _sim(args) -> int:
    import time
    from pathlib import Path

    from hil.nodes import sil
    from hil.cli import (cars_or_exit, design_or_exit, fail, key_or_exit, lock_out,
                         log_options_or_exit, progress_bar)
    from hil.transport.buslog import SIL_CHANNEL, BusLogFile, convert, copies_of
    from hil.config import ConfigError, load_driver_script
    from hil.report.figures import write_outputs
    from hil.nodes import LockstepClock
    from hil.report.render import finish, render_sil

    t0 = time.monotonic()
    cfg, cal = cars_or_exit(args.vehicle, args.calibration)
    route = route_or_exit(args.route)
    opts = design_or_exit(args.design)
    if args.driver == "script" and not args.script:
        fail("sim: --driver script needs --script FILE")
    log = clock = None
    start_us, formats = log_options_or_exit(args)
    if args.out:
        lock_out(args.out)
        # (an earlier run's log copies: only this run's stay; the rest is written anew)
        for copy in copies_of(Path(args.out) / "bus.log"):
            copy.unlink(missing_ok=True)
    try:
        script = load_driver_script(args.script) if args.script else None
        gains = Path(args.gains) if args.gains else None
        # (the ECU's calibration: the calibration car's; sil.run designs the driven car's)
        params = sil.ecu_params(cal, args.mode, opts=opts, gains_file=gains) \
            if cal is not cfg else None
        if args.out:
            log = BusLogFile(Path(args.out) / "bus.log", SIL_CHANNEL, start_us)
            clock = LockstepClock(cfg.sim.plant_dt_s)
        with progress_bar(f"SIL {route.name} ({args.mode})", not args.json) as progress:
            report, trace = sil.run(
                cfg, route, args.mode, args.seed, controller=args.controller,
                gains_file=gains, opts=opts, params=params, policy=args.driver,
                script=script, progress=progress, duration_s=args.duration,
                fixed_point=args.fixed_point, key=key_or_exit(args.key_file),
                on_frame=(lambda fid, data: log.write(fid, data, clock.stamp(fid)))
                if log else None)
    except ConfigError as exc:
        fail(str(exc))
    except OSError as exc:          # bus.log on a full (or vanished) disk: one line, as hil run
        fail(_cannot_write(args.out, exc), 1)
    finally:
        if log is not None:
            try:
                log.close()
            except OSError as exc:
                fail(_cannot_write(args.out, exc), 1)
    if cal is not cfg:
        report["calibration"] = cal.source
    # the ride: every scored segment against its mode's acceptance (hil.validate.ride)
    from hil.validate import ride

    ride.attach(report, cfg, route, params or sil.ecu_params(cfg, args.mode, opts=opts,
                                                             gains_file=gains), opts)
    if args.out:
        try:
            logs = [log.path, *convert(log.path, formats, start_us)]
        except Exception as exc:  # noqa: BLE001 - a writer's own error, said in one line
            fail(f"sim: the bus log could not be converted: {type(exc).__name__}: {exc}", 1)
        report["bench"] = {"harness": "sil", "frames_logged": log.count,
                           "logs": [p.name for p in logs]}
        try:
            write_outputs(Path(args.out), report, trace, cfg, route)
        except OSError as exc:
            fail(_cannot_write(args.out, exc), 1)
    if args.junit:
        verdict.write_junit(args.junit, f"hil sim {route.name} {args.mode}",
                            [verdict.Check(**c) for c in report["checks"]],
                            time.monotonic() - t0)
    finish(report, None, "report.json", args.json, render_sil)
    if args.out and not args.json:
        print(f"report: {Path(args.out) / 'report.md'} (and report.json, bus.log, figures)")
    return verdict.exit_code(report)


def _cannot_write(out: str, exc: OSError) -> str:
    where = f" ({exc.filename})" if exc.filename else ""
    return f"sim: --out {out}: cannot write{where}: {exc.strerror or exc}"


def _run(args) -> int:
    from hil.bench import supervisor
    from hil.bench.spec import RunSpec

    from hil.validate import ride

    return supervisor.run(RunSpec.from_args(args), judge=ride.judge_run)


def _node(args) -> int:
    from hil.bench import procs

    return procs.main(args.command, args)


def _campaign(args) -> int:
    from hil.validate import campaign

    return {"campaign": campaign.main, "campaign-report": campaign.report_main,
            "campaign-case": campaign.case_main}[args.command](args)


def _faults(args) -> int:
    from hil.cli import fail
    from hil.validate import faults, sensorfaults

    if args.sensors:
        return sensorfaults.main(args)
    if args.vehicle or args.route or args.calibration:
        fail("faults: --vehicle, --calibration and --route are the sensor campaign's "
             "(--sensors); the bus campaign drives the default car on its own route")
    return faults.main(args)


def _diag(args) -> int:
    from hil.apps import diag

    return diag.main(args)


def _xcp(args) -> int:
    from hil.apps import xcpcli

    return xcpcli.main(args)


def _alarms(args) -> int:
    from hil.validate import alarms

    return alarms.main(args)


def _cache(args) -> int:
    from calib import cache
    from hil.cli import emit

    removed = cache.clear() if args.clear else 0
    entries = sorted(cache.directory().rglob("*.pickle")) if cache.directory().is_dir() \
        else []
    info = {"directory": str(cache.directory()), "enabled": cache.enabled(),
            "entries": len(entries), "bytes": sum(p.stat().st_size for p in entries),
            "removed": removed}
    emit(info, args.json, lambda r: print(
        f"design cache {r['directory']}: {r['entries']} entries, {r['bytes']} bytes"
        + (f" ({r['removed']} removed)" if args.clear else "")
        + ("" if r["enabled"] else "; off in this environment (SUSPENSION_NO_CACHE)")))
    return 0


def _keygen(args) -> int:
    from hil.cli import fail
    from hil.transport import secoc

    try:
        secoc.write_key(args.file)
    except FileExistsError:
        fail(f"{args.file} exists; a key file is never overwritten")
    except OSError as exc:
        fail(f"{args.file}: {exc.strerror or exc}")
    print(f"wrote {args.file} (AES-128 key, mode 0600)")
    return 0


def _logdiff(args) -> int:
    import json

    from hil.cli import fail
    from hil.transport.buslog import compare, render_compare

    try:
        c = compare(args.reference, args.other)
    except (OSError, ValueError) as exc:
        fail(f"cannot read the logs: {exc}")
    print(json.dumps(c, indent=1) if args.json else render_compare(c))
    return 0 if c["equal"] else 1


def _routes(args) -> int:
    from hil.sim.road import load_route, shipped_routes

    for name in shipped_routes():
        r = load_route(name)
        print(f"{name:20s} {len(r.segments):2d} segments  {r.length_m:7.0f} m  "
              f"{r.duration_s:6.1f} s  {r.description}")
    return 0


def _drive(args) -> int:
    from hil.report.render import drive_report, finish, render_drive

    cfg = vehicle_or_exit(args.vehicle)
    route = route_or_exit(args.route).with_convention(args.convention)
    report = drive_report(cfg, route, args.seed, nonlinear=args.nonlinear,
                          show_progress=not args.json)
    finish(report, args.out, "drive.json", args.json, render_drive)
    return 0


_COMMANDS = {"sim": _sim, "run": _run, "ecu": _node, "plant": _node,
             "app": _node, "campaign": _campaign, "campaign-report": _campaign,
             "campaign-case": _campaign, "faults": _faults, "diag": _diag, "xcp": _xcp,
             "alarms": _alarms,
             "cache": _cache, "keygen": _keygen, "logdiff": _logdiff, "routes": _routes,
             "drive": _drive}

if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
