"""The controller comparison table of the README: every controller on each grade A-D at
20 m/s, SIL with the whole ECU in the loop, RMS ratios to the passive twin.

    python -m tools.controller_table [--seconds 60] [--seed 1] [--vehicle F] [--json]

prints a Markdown table (or JSON), with the exact limits beside it.
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor

from calib.linear import physical_limits
from calib.model import linear_model
from hil.cli import add_json_argument, add_vehicle_argument, emit, positive_float, seed_arg, vehicle_or_exit
from hil.sim.road import constant_route, gq_of

# controller -> the mode it runs in
RUNS = (("bppid", "comfort"), ("pid", "comfort"), ("skyhook", "comfort"), ("lqr", "safety"),
        ("galqr", "comprehensive"), ("regen", "regen"))
GRADES = "ABCD"


def _one(job):
    vehicle, grade, controller, mode, seconds, seed = job
    from hil.nodes import sil
    from hil.config import load_vehicle

    cfg = load_vehicle(vehicle)
    rep, _ = sil.run(cfg, constant_route(grade, 20.0, seconds + sil.SETTLE_S), mode, seed,
                     controller=controller)
    s = rep["segments"][0]
    return grade, controller, s


def table(vehicle: str | None, seconds: float, seed: int, workers: int = 2) -> dict:
    jobs = [(vehicle, g, c, m, seconds, seed) for g in GRADES for c, m in RUNS]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        results = list(pool.map(_one, jobs))
    cfg = vehicle_or_exit(vehicle)
    lim = physical_limits(linear_model(cfg.vehicle, gq_of("B"), 20.0))
    rows = {}
    for grade, controller, s in results:
        row = rows.setdefault(grade, {"passive": s["passive"]})
        row[controller] = {"ratio": s["ratio"], "force_rms_n": s["active"]["force_rms_n"],
                           "harvested_w": s["harvested_w"], "road_power_w": s["road_power_w"]}
    return {"seconds": seconds, "seed": seed, "speed_mps": 20.0, "vehicle": cfg.source,
            "grades": rows,
            "limits": {"comfort_ba_ratio": lim["comfort"].value,
                       "safety_dtd_ratio": lim["safety"].value,
                       "balanced_ratio": lim["balanced"].value,
                       "eq43_fitness": lim["eq43"].value}}


def markdown(o: dict) -> str:
    heads = ["grade", "passive BA / SWS / DTD"] + [c for c, _ in RUNS]
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for g in GRADES:
        row = o["grades"][g]
        p = row["passive"]
        cells = [g, f"{p['ba_rms_mps2']:.3f} m/s² / {p['sws_rms_m'] * 1e3:.2f} / "
                    f"{p['dtd_rms_m'] * 1e3:.2f} mm"]
        for c, _ in RUNS:
            r = row[c]["ratio"]
            cell = f"{r['ba']:.3f} / {r['sws']:.3f} / {r['dtd']:.3f}"
            if c == "regen":
                cell += f" ({row[c]['harvested_w'] / row[c]['road_power_w']:.0%} harvested)"
            cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.controller_table", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_vehicle_argument(parser)
    add_json_argument(parser)
    parser.add_argument("--seconds", type=positive_float, default=60.0)
    parser.add_argument("--seed", type=seed_arg, default=1)
    args = parser.parse_args(argv)
    vehicle_or_exit(args.vehicle)
    out = table(args.vehicle, args.seconds, args.seed)
    emit(out, args.json, lambda o: print(markdown(o)))
    return 0


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
