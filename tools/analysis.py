"""Lyapunov-based analysis: passive RMS, switching thresholds, physical limits of control.

    python -m tools.analysis passive --grade B --speed 20 [--simulate 600 --seed 1] [--json]
    python -m tools.analysis thresholds [--json]
    python -m tools.analysis limits --grade B --speed 20 [--json]

Every sub-command takes ``--vehicle FILE`` and ``--convention iso|paper``.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from hil.cli import (add_json_argument, add_vehicle_argument, emit, fail, grade_arg,
                     positive_float, progress_bar, seed_arg, speed_arg, vehicle_or_exit)
from hil.config import VehicleConfig
from hil.drive import drive
from calib.model import linear_model, paper_thresholds, passive_rms
from hil.road import DEFAULT_CUTOFF_N_PER_M, constant_route, gq_of
from calib.linear import physical_limits

SETTLE_S = 5.0


def _model(cfg: VehicleConfig, grade: str, speed: float, convention: str, cutoff: float):
    return linear_model(cfg.vehicle, gq_of(grade), speed, convention, cutoff)


def passive(cfg: VehicleConfig, grade: str, speed: float, convention: str = "iso",
            cutoff: float = DEFAULT_CUTOFF_N_PER_M, simulate_s: float | None = None,
            seed: int = 0, progress=None) -> dict:
    ba, sws, dtd = passive_rms(_model(cfg, grade, speed, convention, cutoff))
    out = {"grade": grade, "speed_mps": speed, "convention": convention,
           "vehicle": cfg.source, "ba_rms_mps2": ba, "sws_rms_m": sws, "dtd_rms_m": dtd}
    if simulate_s is not None:
        route = constant_route(grade, speed, simulate_s + SETTLE_S, convention, cutoff)
        trace = drive(cfg, route, seed, progress=progress)
        skip = int(round(SETTLE_S / trace.dt_s))
        m = trace.metrics(slice(skip, None))
        out["simulation"] = {
            "seconds": simulate_s, "seed": seed, "settle_s": SETTLE_S,
            "ba_rms_mps2": m.ba_rms_mps2, "sws_rms_m": m.sws_rms_m, "dtd_rms_m": m.dtd_rms_m,
            "ba_wk_rms_mps2": m.ba_wk_rms_mps2,
            "relative_error": {"ba": m.ba_rms_mps2 / ba - 1.0, "sws": m.sws_rms_m / sws - 1.0,
                               "dtd": m.dtd_rms_m / dtd - 1.0},
        }
    return out


def thresholds(cfg: VehicleConfig, convention: str = "iso",
               cutoff: float = DEFAULT_CUTOFF_N_PER_M) -> dict:
    """Eq. (24)-(26): passive RMS values that bound the B and C roads over 10-30 m/s."""
    dtd1, ba1, ba2 = paper_thresholds(cfg.vehicle, convention, cutoff)
    return {"convention": convention, "vehicle": cfg.source, "dtd1_m": dtd1, "ba1_mps2": ba1,
            "ba2_mps2": ba2,
            "definitions": {"dtd1_m": "passive DTD RMS, grade B, 30 m/s (Eq. 24)",
                            "ba1_mps2": "passive BA RMS, grade B, 10 m/s (Eq. 25)",
                            "ba2_mps2": "passive BA RMS, grade C, 30 m/s (Eq. 26)"}}


def limits(cfg: VehicleConfig, grade: str, speed: float, convention: str = "iso",
           cutoff: float = DEFAULT_CUTOFF_N_PER_M) -> dict:
    model = _model(cfg, grade, speed, convention, cutoff)
    res = physical_limits(model)
    ba, sws, dtd = passive_rms(model)
    return {
        "grade": grade, "speed_mps": speed, "convention": convention, "vehicle": cfg.source,
        "comfort_ba_ratio": res["comfort"].value,
        "safety_dtd_ratio": res["safety"].value,
        "balanced_ratio": res["balanced"].value,
        "eq43_fitness": res["eq43"].value,
        "passive": {"ba_rms_mps2": ba, "sws_rms_m": sws, "dtd_rms_m": dtd},
        "details": {name: r.as_dict() for name, r in res.items()},
    }


# -- rendering ---------------------------------------------------------------------------------

def _table(title: str, rows: list[tuple[str, str]]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for name, value in rows:
        table.add_row(name, value)
    Console().print(table)


def _render_passive(o: dict) -> None:
    rows = [("BA RMS (Lyapunov)", f"{o['ba_rms_mps2']:.4f} m/s²"),
            ("SWS RMS (Lyapunov)", f"{o['sws_rms_m'] * 1e3:.3f} mm"),
            ("DTD RMS (Lyapunov)", f"{o['dtd_rms_m'] * 1e3:.3f} mm")]
    if "simulation" in o:
        s = o["simulation"]
        e = s["relative_error"]
        rows += [(f"BA RMS ({s['seconds']:g} s sim, seed {s['seed']})",
                  f"{s['ba_rms_mps2']:.4f} m/s² ({e['ba']:+.2%})"),
                 ("SWS RMS (sim)", f"{s['sws_rms_m'] * 1e3:.3f} mm ({e['sws']:+.2%})"),
                 ("DTD RMS (sim)", f"{s['dtd_rms_m'] * 1e3:.3f} mm ({e['dtd']:+.2%})"),
                 ("BA W_k-weighted RMS (sim)", f"{s['ba_wk_rms_mps2']:.4f} m/s²")]
    _table(f"Passive car, grade {o['grade']}, {o['speed_mps']:g} m/s, {o['convention']} PSD", rows)


def _render_thresholds(o: dict) -> None:
    _table(f"Switching thresholds, {o['convention']} PSD",
           [("(z_t - z_f)_1  DTD, B @ 30 m/s", f"{o['dtd1_m'] * 1e3:.4f} mm"),
            ("z̈_s1  BA, B @ 10 m/s", f"{o['ba1_mps2']:.4f} m/s²"),
            ("z̈_s2  BA, C @ 30 m/s", f"{o['ba2_mps2']:.4f} m/s²")])


def _render_limits(o: dict) -> None:
    d = o["details"]

    def ratios(name: str) -> str:
        r = d[name]["ratios"]
        return f"BA {r['ba']:.3f}  SWS {r['sws']:.3f}  DTD {r['dtd']:.3f}"

    _table(f"Physical limits of any causal controller, grade {o['grade']}, {o['speed_mps']:g} m/s",
           [("comfort: min BA/BA_p, SWS and DTD <= passive", f"{o['comfort_ba_ratio']:.4f}"),
            ("   at", ratios("comfort")),
            ("safety: min DTD/DTD_p, BA and SWS <= passive", f"{o['safety_dtd_ratio']:.4f}"),
            ("   at", ratios("safety")),
            ("balanced: min t, all ratios <= t", f"{o['balanced_ratio']:.4f}"),
            ("Eq. (43) fitness under Eq. (44)", f"{o['eq43_fitness']:.4f}"),
            ("   at", ratios("eq43"))])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.analysis", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        add_vehicle_argument(p)
        add_json_argument(p)
        p.add_argument("--convention", choices=("iso", "paper"), default="iso",
                       help="road PSD convention (errata 5; default iso)")
        p.add_argument("--cutoff", type=positive_float, default=DEFAULT_CUTOFF_N_PER_M,
                       metavar="N_PER_M", help="road lower cut-off, spatial (default 0.005 1/m)")

    p = sub.add_parser("passive", help="exact passive RMS of BA, SWS, DTD")
    common(p)
    p.add_argument("--grade", type=grade_arg, required=True)
    p.add_argument("--speed", type=speed_arg, required=True, metavar="MPS")
    p.add_argument("--simulate", type=positive_float, metavar="SECONDS",
                   help="also simulate this long in the time domain")
    p.add_argument("--seed", type=seed_arg, default=0)
    p = sub.add_parser("thresholds", help="mode-switching thresholds of Eq. (24)-(26)")
    common(p)
    p = sub.add_parser("limits", help="exact limits of any causal controller")
    common(p)
    p.add_argument("--grade", type=grade_arg, required=True)
    p.add_argument("--speed", type=speed_arg, required=True, metavar="MPS")
    args = parser.parse_args(argv)
    cfg = vehicle_or_exit(args.vehicle)

    try:
        if args.command == "passive":
            with progress_bar("simulating", bool(args.simulate) and not args.json) as progress:
                out = passive(cfg, args.grade, args.speed, args.convention, args.cutoff,
                              args.simulate, args.seed, progress)
            render = _render_passive
        elif args.command == "thresholds":
            out, render = thresholds(cfg, args.convention, args.cutoff), _render_thresholds
        else:
            out = limits(cfg, args.grade, args.speed, args.convention, args.cutoff)
            render = _render_limits
    except (ValueError, np.linalg.LinAlgError) as exc:   # a design the analysis cannot do
        fail(f"{cfg.source}: {args.command}: {exc}")
    if not _all_finite(out):
        fail(f"{cfg.source}: {args.command}: the results are not finite (check the vehicle)")
    emit(out, args.json, render)
    return 0


def _all_finite(value) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_all_finite(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_all_finite(v) for v in value)
    return True


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
