"""Lyapunov-based analysis: passive RMS, switching thresholds, physical limits of control.

    python -m tools.analysis passive --grade B --speed 20 [--simulate 600 --seed 1] [--json]
    python -m tools.analysis thresholds [--json]
    python -m tools.analysis limits --grade B --speed 20 [--json]
    python -m tools.analysis scatter --window 60 [--speed 20] [--json]

Every sub-command takes ``--vehicle FILE`` and ``--convention iso|paper``.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from calib.linear import physical_limits
from calib.model import linear_model, paper_thresholds, passive_rms, window_scatter
from calib.vehicle import VehicleConfig
from hil.cli import (add_json_argument, add_vehicle_argument, emit, fail, grade_arg,
                     positive_float, progress_bar, seed_arg, speed_arg, vehicle_or_exit)
from hil.sim.drive import drive
from hil.sim.road import DEFAULT_CUTOFF_N_PER_M, constant_route, gq_of

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


def scatter(cfg: VehicleConfig, speed: float, window_s: float, convention: str = "iso",
            cutoff: float = DEFAULT_CUTOFF_N_PER_M) -> dict:
    """How far one drive of ``window_s`` can be trusted: for the ECU's safety and comfort
    designs (built for this vehicle at the nominal speed, ``calib.ecu_params``; comfort as its
    linear design, whose skyhook the BP-PID carries), the exact ratios to passive at
    ``speed``, the standard deviation of the log of a ratio measured over the drive
    (``calib.model.window_scatter``), the chance that it comes out above 1.0, and the drive
    a ratio needs to stay below 1.0 at 3 sigma (the approximation holds for drives much
    longer than the body's period: read a few seconds as "any drive")."""
    from calib.control_design import comfort_total_gain, safety_gain
    from calib.options import NOMINAL_SPEED_MPS, DesignOptions

    opts = DesignOptions()
    nominal = linear_model(cfg.vehicle, gq_of("C"), NOMINAL_SPEED_MPS, convention, cutoff)
    gains = {"safety": safety_gain(nominal, opts).K,
             "comfort": comfort_total_gain(cfg, opts, nominal).K}
    model = _model(cfg, "C", speed, convention, cutoff)
    out = {"speed_mps": speed, "window_s": window_s, "convention": convention,
           "vehicle": cfg.source, "designs": {}}
    for name, K in gains.items():
        ratios, sigma = window_scatter(model, K, window_s)
        d = {"ratio": {}, "sigma_log": {}, "p_over_1": {}, "drive_for_3_sigma_s": {}}
        for i, key in enumerate(("ba", "sws", "dtd")):
            r, s = float(ratios[i]), float(sigma[i])
            d["ratio"][key], d["sigma_log"][key] = r, s
            d["p_over_1"][key] = 0.5 * math.erfc(-math.log(r) / (s * math.sqrt(2.0)))
            # sigma falls as 1/sqrt(T): 3 sigma(T) = -ln r at T = window (3 sigma / -ln r)^2
            d["drive_for_3_sigma_s"][key] = (window_s * (3.0 * s / -math.log(r)) ** 2
                                             if r < 1.0 else None)
        out["designs"][name] = d
    return out


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


def _render_scatter(o: dict) -> None:
    rows = []
    for name, d in o["designs"].items():
        for key in ("ba", "sws", "dtd"):
            need = d["drive_for_3_sigma_s"][key]
            rows.append((f"{name}: {key.upper()} ratio", f"{d['ratio'][key]:.3f} "
                         f"± {d['sigma_log'][key]:.1%}, P(> 1) {d['p_over_1'][key]:.2%}, "
                         + (f"3σ below 1 from {need:.0f} s" if need is not None else "never below 1")))
    _table(f"A ratio over one drive of {o['window_s']:g} s at {o['speed_mps']:g} m/s", rows)


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
    p = sub.add_parser("scatter", help="how much the ECU designs' ratios scatter on one drive")
    common(p)
    p.add_argument("--window", type=positive_float, default=60.0, metavar="SECONDS",
                   help="the drive's length (default 60 s)")
    p.add_argument("--speed", type=speed_arg, default=20.0, metavar="MPS")
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
        elif args.command == "scatter":
            out = scatter(cfg, args.speed, args.window, args.convention, args.cutoff)
            render = _render_scatter
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
