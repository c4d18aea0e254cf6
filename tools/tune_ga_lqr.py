"""GA-LQR tuning for the comprehensive mode (``calib.galqr``, paper §5.3, Eq. (39)-(44)):

    python -m tools.tune_ga_lqr [--vehicle F] [--seed N] [--simulate SECONDS] [--out FILE] --json

writes the gains file the ECU loads (default: calib/gains/galqr_<vehicle digest>.json).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from calib.control_design import default_gains_path
from calib.galqr import tune, vehicle_digest
from calib.options import NOMINAL_SPEED_MPS
from calib.vehicle import VehicleConfig
from hil.cli import add_json_argument, add_vehicle_argument, emit, positive_float, seed_arg, vehicle_or_exit
from hil.nodes import sil
from hil.sim.road import constant_route


def confirm_by_simulation(cfg: VehicleConfig, K: list, seconds: float, seed: int) -> dict:
    """Time-domain confirmation: the whole ECU in the loop (SIL), comprehensive mode, D road."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "gains.json"
        path.write_text(json.dumps({"K": K, "vehicle_sha256": vehicle_digest(cfg)}))
        rep, _ = sil.run(cfg, constant_route("D", NOMINAL_SPEED_MPS, seconds + sil.SETTLE_S),
                         "comprehensive", seed, gains_file=path)
    r = rep["segments"][0]["ratio"]
    return {"seconds": seconds, "seed": seed, "ratios": r, "fitness": sum(r.values())}


def write_gains(result: dict, path: Path) -> Path:
    from hil.cli import write_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    keep = {k: v for k, v in result.items() if k not in ("vehicle", "simulation", "gains_file")}
    return write_atomic(path, json.dumps(keep, indent=2) + "\n")


def _render(o: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"GA-LQR (seed {o['seed']}, {o['evaluations']} evaluations)")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    t.add_row("q (BA, SWS, DTD)", ", ".join(f"{x:.4g}" for x in o["q"]))
    t.add_row("K (zs', zt', zs, zt, zf)", ", ".join(f"{x:.1f}" for x in o["K"]))
    r = o["ratios"]
    t.add_row("ratios BA / SWS / DTD", f"{r['ba']:.4f} / {r['sws']:.4f} / {r['dtd']:.4f}")
    t.add_row("fitness, Eq. (43)", f"{o['fitness']:.4f}")
    if "simulation" in o:
        s = o["simulation"]
        t.add_row(f"SIL {s['seconds']:g} s fitness", f"{s['fitness']:.4f}")
    t.add_row("gains file", o["gains_file"])
    Console().print(t)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.tune_ga_lqr", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_vehicle_argument(parser)
    add_json_argument(parser)
    parser.add_argument("--seed", type=seed_arg, default=0)
    parser.add_argument("--simulate", type=positive_float, metavar="SECONDS",
                        help="confirm the result by a SIL simulation this long")
    parser.add_argument("--out", metavar="FILE", help="gains file to write "
                        "(default: calib/gains/galqr_<vehicle digest>.json)")
    args = parser.parse_args(argv)
    cfg = vehicle_or_exit(args.vehicle)
    result = tune(cfg, args.seed)
    if not result["feasible"]:
        print("error: the GA found no weights satisfying Eq. (44) with the design margin",
              file=sys.stderr)
        return 1
    path = write_gains(result, Path(args.out) if args.out else default_gains_path(cfg))
    result["gains_file"] = str(path)
    if args.simulate:
        result["simulation"] = confirm_by_simulation(cfg, result["K"], args.simulate, args.seed)
    emit(result, args.json, _render)
    return 0


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
