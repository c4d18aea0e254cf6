"""How far each parameter may leave a car's calibration, one at a time, before a drive fails.

    python -m tools.tolerance [--vehicle FILE] [--route FILE|NAME] [--seed 1] [--steps 6]
                              [--parameters KEY ...] [--duration S] [--json]

The car keeps its base calibration (a campaign space's ``nominal``: the payload sags it),
one parameter moves, and the case is judged as a campaign judges it (the drive's verdict
checks, among them no fail-safe and no confirmed DTC, and the acceptance relative to the
car's own limit). Per parameter and direction, over the range ``load_and_wear.toml``
samples: either the whole range passes, or a bisection (``--steps`` halvings) brackets the
first failure between the last factor that passes and the first that fails, with what
failed there. Exit 0 when every range passes, 1 otherwise."""

from __future__ import annotations

import argparse
from pathlib import Path

from hil.cli import add_json_argument, emit, fail, positive_float, progress_bar, seed_arg

ROOT = Path(__file__).resolve().parents[1]
# the ranges of campaigns/load_and_wear.toml: (key, the ends a car meets)
RANGES = (("sprung_mass_kg", (1.3,)), ("damping_n_s_per_m", (0.7,)),
          ("spring_stiffness_n_per_m", (0.9, 1.1)), ("unsprung_mass_kg", (0.9, 1.1)),
          ("tire_stiffness_n_per_m", (0.8, 1.2)), ("torque_constant_nm_per_a", (0.9, 1.1)),
          ("winding_resistance_ohm", (0.9, 1.1)))


def case(vehicle: str | None, route: dict, seed: int, key: str, factor: float,
         duration_s: float | None = None) -> dict:
    """The campaign case of the base car with one factor, on its nominal calibration, with
    its bump stops."""
    from hil.validate.campaign.spec import new_case

    text = Path(vehicle).read_text() if vehicle else None
    name = Path(vehicle).stem if vehicle else "default"
    return new_case(route, seed, {"name": name, "toml": text, "factors": {key: factor},
                                  "nonlinear": {"bump_stops": True}, "sample": 1,
                                  "calibration": "nominal"}, duration_s=duration_s)


def tolerance(vehicle: str | None, route: dict, seed: int, steps: int, progress=None,
              keys: tuple[str, ...] = (), duration_s: float | None = None) -> list[dict]:
    from hil.validate.campaign.case import run_case

    jobs = [(k, end) for k, ends in RANGES for end in ends if not keys or k in keys]
    out, done, total = [], 0, len(jobs) * (1 + steps)

    def judged(key: str, f: float) -> tuple[bool, list]:
        nonlocal done
        res = run_case(case(vehicle, route, seed, key, f, duration_s), acceptance="relative")
        done += 1
        if progress:
            progress(done, total)
        return res["verdict"] == "pass", res["failed"]

    for key, end in jobs:
        ok, why = judged(key, end)
        row = {"parameter": key, "range_end": end, "whole_range": ok}
        if not ok:
            good, bad = 1.0, end
            for _ in range(steps):
                mid = round((good + bad) / 2, 6)
                mid_ok, mid_why = judged(key, mid)
                if mid_ok:
                    good = mid
                else:
                    bad, why = mid, mid_why
            row.update(passes_at=good, fails_at=bad, failed=why)
        done = (jobs.index((key, end)) + 1) * (1 + steps)       # (a whole range: no steps)
        if progress:
            progress(done, total)
        out.append(row)
    return out


def _render(o: dict) -> None:
    from rich.console import Console

    con = Console()
    con.print(f"{o['vehicle']} on its own calibration, {o['route']} seed {o['seed']}: "
              "each parameter alone")
    for r in o["rows"]:
        if r["whole_range"]:
            con.print(f"  {r['parameter']} to x{r['range_end']:g}: passes")
        else:
            con.print(f"  {r['parameter']} towards x{r['range_end']:g}: passes at "
                      f"x{r['passes_at']:g}, fails at x{r['fails_at']:g} "
                      f"({'; '.join(r['failed'])})", soft_wrap=True)
    con.print(f"verdict: {o['verdict'].upper()}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.tolerance", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vehicle", metavar="FILE", default=None,
                   help="the base car's vehicle file (default: the paper's Table 3 car)")
    p.add_argument("--route", default=str(ROOT / "campaigns" / "acceptance_route.toml"),
                   help="a shipped route's name or a route file (default: the acceptance "
                        "route)")
    p.add_argument("--seed", type=seed_arg, default=1)
    p.add_argument("--steps", type=int, default=6, choices=range(1, 13), metavar="N",
                   help="bisection halvings per failing range (default 6)")
    p.add_argument("--parameters", nargs="+", metavar="KEY", default=(),
                   choices=[k for k, _ in RANGES], help="only these parameters (default: all)")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="stop each drive after S seconds (default: the whole route)")
    add_json_argument(p)
    args = p.parse_args(argv)
    from calib.errors import ConfigError
    from hil.config import load_vehicle
    from hil.sim.road import load_route

    try:
        if args.vehicle:
            load_vehicle(args.vehicle)
        load_route(args.route)
    except (ConfigError, OSError, ValueError) as exc:
        fail(str(exc))
    route = ({"name": Path(args.route).stem, "toml": Path(args.route).read_text()}
             if args.route.endswith(".toml") else {"name": args.route})
    with progress_bar("tolerance", not args.json) as bar:
        rows = tolerance(args.vehicle, route, args.seed, args.steps, bar,
                         tuple(args.parameters), args.duration)
    o = {"vehicle": args.vehicle or "default", "route": route["name"], "seed": args.seed,
         "rows": rows, "verdict": "pass" if all(r["whole_range"] for r in rows) else "fail"}
    emit(o, args.json, _render)
    return 0 if o["verdict"] == "pass" else 1


if __name__ == "__main__":
    raise SystemExit(main())
