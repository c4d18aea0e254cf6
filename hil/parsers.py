"""``python -m hil``'s grammar: every command's options (``hil.__main__`` parses with them and
runs the command)."""

from __future__ import annotations

import argparse
import os

from hil import config
from hil.cli import (add_cache_argument, add_calibration_argument, add_design_argument,
                     add_json_argument, add_log_arguments, add_vehicle_argument, positive_float,
                     positive_int, seed_arg)
from hil.report import verdict


def add_commands(sub, bus_parsers: bool) -> None:
    """Every command's parser; the bus commands' (their options are python-can's) only when
    ``bus_parsers``."""
    _tool_parsers(sub, bus_parsers)
    _campaign_parsers(sub)
    _sim_parser(sub)
    if bus_parsers:
        _node_parsers(sub)
        _faults_parser(sub)


def _tool_parsers(sub, bus_parsers: bool) -> None:
    p = sub.add_parser("drive", help="drive the passive car along a route; RMS per segment "
                                     "against the exact (Lyapunov) values")
    p.add_argument("--route", default="full_road_section",
                   help="route TOML file or shipped route name (default: full_road_section)")
    p.add_argument("--seed", type=seed_arg, default=1)
    p.add_argument("--convention", choices=("iso", "paper"), default=None,
                   help="override the route's road PSD convention")
    p.add_argument("--nonlinear", action="store_true",
                   help="enable bump stops and tyre lift-off whatever the vehicle file says")
    p.add_argument("--out", metavar="DIR", help="write DIR/drive.json")
    add_vehicle_argument(p)
    add_json_argument(p)
    sub.add_parser("routes", help="list the shipped routes")
    sub.add_parser("vcan", help="run a command (or a shell) in User-mode Linux with SocketCAN "
                                "and vcan0 up (python -m hil vcan --help)", add_help=False)
    p = sub.add_parser("logdiff", help="compare two candump logs frame by frame (IDs, "
                                       "payloads, order; timestamps aside); exit 1 if they "
                                       "differ")
    p.add_argument("reference", metavar="LOG")
    p.add_argument("other", metavar="LOG")
    add_json_argument(p)
    from hil.validate import alarms

    if bus_parsers:
        from hil.apps import diag, xcpcli

        diag.add_parser(sub)
        xcpcli.add_parser(sub)
    alarms.add_parser(sub)
    p = sub.add_parser("keygen", help="write a new SecOC key file (16 random bytes, mode 0600)")
    p.add_argument("file", metavar="FILE")
    p = sub.add_parser("cache", help="the design cache (calib/cache.py): where it is and what "
                                     "it holds; --clear empties it")
    p.add_argument("--clear", action="store_true")
    add_json_argument(p)


def _campaign_parsers(sub) -> None:
    p = sub.add_parser("campaign", help="a validation campaign (a matrix of SIL cases) on "
                                        "Dask, results in SQLite (hil/validate/campaign.py)")
    p.add_argument("file", metavar="FILE.toml")
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster, one worker process per core) or "
                        "tcp://127.0.0.1:PORT (a running dask scheduler)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local: worker processes (default: one per core)")
    p.add_argument("--out", metavar="DIR", help="database and report (default: "
                   "out/campaign/NAME)")
    add_cache_argument(p)
    add_json_argument(p)
    p = sub.add_parser("campaign-case", help="run one case of a campaign database again "
                                             "(the reproduce column of campaign-report)")
    p.add_argument("db", metavar="DB")
    p.add_argument("case_id", metavar="CASE_ID")
    p = sub.add_parser("campaign-report", help="the summary of a campaign database")
    p.add_argument("db", metavar="DB")
    p.add_argument("--out", metavar="DIR", help="where the figures go (default: beside DB)")
    p.add_argument("--cars", metavar="FILE.md", help="also write every failing and infeasible "
                   "sampled car, with what failed and its command, as Markdown")
    add_json_argument(p)


def _sim_parser(sub) -> None:
    p = sub.add_parser("sim", help="software-in-the-loop: the whole ECU against the plant, "
                                   "with a passive twin on the same road")
    p.add_argument("--route", default="full_road_section",
                   help="route TOML file or shipped route name (default: full_road_section)")
    p.add_argument("--mode", default="auto", choices=MODE_CHOICES,
                   help="auto: the emulated driver accepts recommendations after a reaction "
                        "delay; otherwise the driver chooses this mode and refuses the rest")
    p.add_argument("--controller", choices=CONTROLLER_CHOICES,
                   help="override the controller of the mode (of comfort mode for auto)")
    p.add_argument("--seed", type=seed_arg, default=1)
    p.add_argument("--gains", metavar="FILE", help="GA-LQR gains file (default: the shipped "
                   "one for this vehicle, or tuned on the fly)")
    add_design_argument(p)
    p.add_argument("--duration", type=positive_float, metavar="S",
                   help="stop after S simulated seconds (default: the whole route)")
    p.add_argument("--out", metavar="DIR", help="write DIR/report.json, report.md, figures "
                   "and DIR/bus.log (every frame, candump -L)")
    add_log_arguments(p)
    _fixed_argument(p)
    _key_argument(p)
    add_vehicle_argument(p)
    add_calibration_argument(p)
    add_json_argument(p)
    verdict.add_arguments(p)
    _driver_arguments(p)


MODE_CHOICES = config.MODE_CHOICES
RUN_OUT_HELP = ("write bus.log, report.json, report.md, the figures, each node's record and "
                "log, and the run's SecOC key (secoc.key) into DIR (default: out/run)")
CONTROLLER_CHOICES = tuple(config.CONTROLLERS)


def _web_port_argument(p) -> None:
    p.add_argument("--web-port", type=int, default=0, metavar="N",
                   help="the driver page's port on 127.0.0.1 (default: a free one, printed)")


def _driver_arguments(p, bench: bool = False) -> None:
    extra = ("web", "interactive") if bench else ()
    p.add_argument("--driver", choices=("auto", "fixed", "refuse", "script", *extra),
                   help="driver policy (default: auto for --mode auto, else fixed: choose the "
                        "mode, refuse every recommendation)" + (
                            "; web: the driver app as a page on 127.0.0.1 (its URL printed), "
                            "a person accepts, refuses or chooses" if bench else ""))
    if bench:
        _web_port_argument(p)
    p.add_argument("--script", metavar="FILE", help="driver script TOML ([[request]] tables "
                   "with t_s, kind = accept|refuse|choose, mode)")


def _key_argument(p, node: bool = False) -> None:
    p.add_argument("--key-file", metavar="FILE",
                   help="the SecOC key file (hil/transport/secoc.py; python -m hil keygen FILE)"
                        + (" (required; hil run makes one per run)" if node else
                           " (default: a new key for this run)"))


def _fixed_argument(p) -> None:
    p.add_argument("--fixed-point", action="store_true",
                   help="run the ECU's control path in integer arithmetic (firmware/fixed.py, "
                        "the path c/ecu_fx.c mirrors) instead of float")


def _node_parsers(sub) -> None:
    from can.cli import add_bus_arguments

    def common(p, pace=True, out_help="write DIR/<node>.json and .npz at the end (default: "
                                       "print the summary)"):
        add_bus_arguments(p)
        p.add_argument("--out", metavar="DIR", help=out_help)
        _key_argument(p, node=out_help != RUN_OUT_HELP)
        add_vehicle_argument(p)
        if pace:
            p.add_argument("--pace", choices=("lockstep", "realtime"), default="lockstep",
                           help="default lockstep (hil run --driver web: realtime)")
        p.add_argument("--rt-priority", type=int, default=0, metavar="N",
                       help="SCHED_FIFO priority N (0: normal scheduling, a node's default). "
                            "hil run: the base priority, 50 in realtime pacing and 0 in "
                            "lockstep unless given; plant +10, hub +5, ECU 0, app -5")

    p = sub.add_parser("run", help="the bench: hub, ECU, plant and driver app as processes on "
                                   "a CAN bus; bus.log, report.json/.md and figures in --out")
    p.add_argument("--route", default="full_road_section")
    p.add_argument("--mode", default="auto", choices=MODE_CHOICES)
    p.add_argument("--controller", choices=CONTROLLER_CHOICES)
    p.add_argument("--seed", type=seed_arg, default=1)
    p.add_argument("--gains", metavar="FILE")
    add_design_argument(p)
    p.add_argument("--duration", type=positive_float, metavar="S",
                   help="stop after S simulated seconds (default: the whole route)")
    _driver_arguments(p, bench=True)
    _fixed_argument(p)
    add_log_arguments(p)
    common(p, out_help=RUN_OUT_HELP)
    add_calibration_argument(p)
    p.set_defaults(out="out/run", rt_priority=None, pace=None)   # (pace: see supervisor.run)
    add_json_argument(p)
    verdict.add_arguments(p, realtime=True)
    p.add_argument("--allow-external-tx", action="store_true",
                   help="let hub clients that are not bench nodes send (injection tests; by "
                        "default they are read-only and their frames are dropped)")
    p.add_argument("--stall-s", type=positive_float, default=None, metavar="S",
                   help="stop the run when a node (or the hub) makes no progress for S wall "
                        "seconds (default 20)")

    p = sub.add_parser("plant", help="the plant simulator node (owns simulated time; start it "
                                     "after the ECU and the app)")
    p.add_argument("--route", default="full_road_section")
    p.add_argument("--seed", type=seed_arg, default=1)
    p.add_argument("--duration", type=positive_float, metavar="S")
    _inject_argument(p)
    common(p)
    p.add_argument("--calibration", metavar="FILE",
                   help="the vehicle file the ECU is calibrated for: the plant drives "
                        "--vehicle at that car's ride height (default: its own)")

    p = sub.add_parser("ecu", help="the ECU node (firmware behind its CAN path)")
    p.add_argument("--mode", default="auto", choices=MODE_CHOICES,
                   help="only used with --controller (the mode whose controller it replaces)")
    p.add_argument("--controller", choices=CONTROLLER_CHOICES)
    p.add_argument("--gains", metavar="FILE")
    p.add_argument("--ticks", type=positive_int, metavar="N", help="realtime: the drive's "
                   "samples; after the last, no timer ticks (the drive is over; hil run sets it)")
    add_design_argument(p)
    _fixed_argument(p)
    common(p)

    p = sub.add_parser("app", help="the driver-app emulator node")
    p.add_argument("--policy", choices=("auto", "fixed", "refuse", "script", "interactive",
                                        "web"),
                   help="default: auto for --mode auto, else fixed; interactive: keys in this "
                        "terminal; web: a page on 127.0.0.1 (the port printed)")
    p.add_argument("--web", action="store_const", const="web", dest="policy",
                   help="the same as --policy web")
    _web_port_argument(p)
    p.add_argument("--mode", default="auto", choices=MODE_CHOICES,
                   help="the mode a fixed driver chooses")
    p.add_argument("--script", metavar="FILE")
    p.add_argument("--reaction-s", type=positive_float, default=1.0,
                   help="auto policy: accept a recommendation shown this long (simulated s)")
    p.add_argument("--quiet", action="store_true", help="do not print the requests sent")
    _inject_argument(p)
    common(p)


def _faults_parser(sub) -> None:
    from can.cli import add_bus_arguments

    p = sub.add_parser("faults", help="reliability: the fault-injection campaign over the bus; "
                                      "a table (or --json), DIR/faults.json; exit 1 if a fault "
                                      "is missed, crashes a node or is handled too late")
    p.add_argument("--only", metavar="NAMES", help="comma-separated fault names (default: all)")
    p.add_argument("--seed", type=seed_arg, default=1)
    p.add_argument("--in-process", action="store_true",
                   help="the three nodes in one process instead of processes on a bus")
    from hil.validate.alarms import seeds_arg
    from hil.validate.sensorfaults import DEFAULT_SEEDS, DEFAULT_VEHICLES

    s = p.add_argument_group("the sensor campaign (--sensors): every single-sensor fault of "
                             "the isolability analysis, persistent, one SIL drive each")
    s.add_argument("--sensors", action="store_true",
                   help="run the sensor campaign instead of the bus campaign; writes "
                        "DIR/sensor-faults.json and .md")
    s.add_argument("--vehicle", metavar="FILES",
                   help=f"comma-separated vehicle files (default: {','.join(DEFAULT_VEHICLES)})")
    s.add_argument("--calibration", metavar="FILE",
                   help="the vehicle file the ECU is calibrated for, for every --vehicle "
                        "(default: each car's own): the plant drives each car at that car's "
                        "ride height, the ECU carries its calibration and the analysis is its")
    s.add_argument("--route", help="a route file or shipped name (default: one segment of "
                                   "grade B at 20 m/s)")
    s.add_argument("--seeds", type=seeds_arg, default=list(DEFAULT_SEEDS),
                   help=f"N (1..N) or A-B (default: {DEFAULT_SEEDS[0]}-{DEFAULT_SEEDS[-1]}, "
                        "held out from tuning)")
    s.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="parallel processes (default: one per core)")
    add_bus_arguments(p)
    p.add_argument("--out", metavar="DIR", default="out/faults",
                   help="bus.log, node records and faults.json (default: out/faults)")
    add_cache_argument(p)
    add_json_argument(p)
    verdict.add_arguments(p)


def _inject_argument(p) -> None:
    p.add_argument("--inject", metavar="PLAN", help=argparse.SUPPRESS)   # hil faults' plan
