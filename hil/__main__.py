"""``python -m hil``: the bench's command line.

    python -m hil sim --route full_road_section --mode auto --seed 1 [--controller C] [--json]
    python -m hil drive --route full_road_section --seed 1 [--out DIR] [--json]
    python -m hil routes
"""

from __future__ import annotations

import argparse
import sys

from hil.cli import add_json_argument, add_vehicle_argument, route_or_exit, seed_arg, vehicle_or_exit


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hil", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
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
    p = sub.add_parser("sim", help="software-in-the-loop: the whole ECU against the plant, "
                                   "with a passive twin on the same road")
    p.add_argument("--route", default="full_road_section",
                   help="route TOML file or shipped route name (default: full_road_section)")
    p.add_argument("--mode", default="auto",
                   choices=("auto", "passive", "comfort", "safety", "comprehensive", "regen"),
                   help="auto: the emulated driver accepts recommendations after a reaction "
                        "delay; otherwise the driver chooses this mode and refuses the rest")
    p.add_argument("--controller", choices=("pid", "bppid", "lqr", "galqr", "skyhook", "regen"),
                   help="override the controller of the mode (of comfort mode for auto)")
    p.add_argument("--seed", type=seed_arg, default=1)
    p.add_argument("--gains", metavar="FILE", help="GA-LQR gains file (default: the shipped "
                   "one for this vehicle, or tuned on the fly)")
    p.add_argument("--out", metavar="DIR", help="write DIR/report.json")
    add_vehicle_argument(p)
    add_json_argument(p)
    args = parser.parse_args(argv)

    if args.command == "sim":
        return _sim(args)

    if args.command == "routes":
        from hil.road import load_route, shipped_routes

        for name in shipped_routes():
            r = load_route(name)
            print(f"{name:20s} {len(r.segments):2d} segments  {r.length_m:7.0f} m  "
                  f"{r.duration_s:6.1f} s  {r.description}")
        return 0

    from hil.report import drive_report, finish, render_drive

    cfg = vehicle_or_exit(args.vehicle)
    route = route_or_exit(args.route).with_convention(args.convention)
    report = drive_report(cfg, route, args.seed, nonlinear=args.nonlinear,
                          show_progress=not args.json)
    finish(report, args.out, "drive.json", args.json, render_drive)
    return 0


def _sim(args) -> int:
    from pathlib import Path

    from hil import sil
    from hil.cli import fail, progress_bar
    from hil.config import ConfigError
    from hil.report import finish, render_sil

    cfg = vehicle_or_exit(args.vehicle)
    route = route_or_exit(args.route)
    try:
        with progress_bar(f"SIL {route.name} ({args.mode})", not args.json) as progress:
            report, _ = sil.run(cfg, route, args.mode, args.seed, controller=args.controller,
                                gains_file=Path(args.gains) if args.gains else None,
                                progress=progress)
    except ConfigError as exc:
        fail(str(exc))
    finish(report, args.out, "report.json", args.json, render_sil)
    return 0


if __name__ == "__main__":
    sys.exit(main())
