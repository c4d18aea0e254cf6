"""Reports of drives: per-segment metrics as JSON and as rich tables."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from calib.model import linear_model, passive_rms
from calib.vehicle import VehicleConfig
from hil.cli import progress_bar
from hil.report.figures import ENERGY_COLUMNS, switches_phrase
from hil.sim.drive import drive, segment_masks
from hil.sim.road import Route

SEGMENT_SETTLE_S = 3.0


def drive_report(cfg: VehicleConfig, route: Route, seed: int, *, nonlinear: bool = False,
                 show_progress: bool = False) -> dict:
    if nonlinear:
        nl = dataclasses.replace(cfg.nonlinear, bump_stops=True, tire_lift_off=True)
        cfg = dataclasses.replace(cfg, nonlinear=nl)
    with progress_bar(f"driving {route.name}", show_progress) as progress:
        trace = drive(cfg, route, seed, progress=progress)
    segments = []
    for seg, mask in zip(route.segments, segment_masks(trace, SEGMENT_SETTLE_S)):
        m = trace.metrics(mask)
        exact = passive_rms(linear_model(cfg.vehicle, seg.gq_m3, seg.speed_mps,
                                         route.road.convention, route.road.cutoff_n_per_m))
        segments.append({
            "grade": seg.grade, "gq_m3": seg.gq_m3, "speed_mps": seg.speed_mps,
            "length_m": seg.length_m, "duration_s": seg.duration_s(),
            "passive": m.as_dict(),
            "lyapunov": {"ba_rms_mps2": exact[0], "sws_rms_m": exact[1], "dtd_rms_m": exact[2]},
        })
    whole = trace.metrics()
    return {
        "route": route.name, "seed": seed, "vehicle": cfg.source,
        "convention": route.road.convention, "duration_s": len(trace.timeline) * trace.dt_s,
        "nonlinear": {"bump_stops": cfg.nonlinear.bump_stops,
                      "tire_lift_off": cfg.nonlinear.tire_lift_off},
        "segment_settle_s": SEGMENT_SETTLE_S,
        "segments": segments, "whole_route": whole.as_dict(),
    }


def finish(report: dict, out_dir: str | None, name: str, as_json: bool, render) -> None:
    """Write ``out_dir/name`` (if asked), then print the report as JSON or a table."""
    from hil.cli import emit

    if out_dir:
        path = write_json(report, out_dir, name)
        if not as_json:
            print(f"report written to {path}")
    emit(report, as_json, render)


def write_json(report: dict, out_dir: str | Path, name: str) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from hil.cli import write_atomic

    return write_atomic(out / name, json.dumps(report, indent=2) + "\n")


def render_drive(report: dict) -> None:
    from rich import box
    from rich.console import Console
    from rich.table import Table

    table = Table(box=box.SIMPLE_HEAD, title=f"Passive car, route '{report['route']}', seed {report['seed']}, "
                        f"{report['convention']} PSD",
                  caption="seg = grade@speed (m/s). RMS per segment, simulated; * = exact (Lyapunov). BA in m/s², "
                          "SWS/DTD in mm; Wk = ISO 2631-1 weighted BA; bump-stop contacts, tyre lift-offs")
    for col in ("seg", "BA", "BA*", "SWS", "SWS*", "DTD", "DTD*", "Wk", "stop",
                "lift"):
        table.add_column(col, justify="right", no_wrap=True, min_width=5)
    for s in report["segments"]:
        p, e = s["passive"], s["lyapunov"]
        table.add_row(f"{s['grade']}@{s['speed_mps']:g}", f"{p['ba_rms_mps2']:.3f}",
                      f"{e['ba_rms_mps2']:.3f}", f"{p['sws_rms_m'] * 1e3:.2f}",
                      f"{e['sws_rms_m'] * 1e3:.2f}", f"{p['dtd_rms_m'] * 1e3:.2f}",
                      f"{e['dtd_rms_m'] * 1e3:.2f}", f"{p['ba_wk_rms_mps2']:.3f}",
                      str(p["bump_stop_contacts"]), str(p["tire_lift_off_events"]))
    Console().print(table)


def render_sil(report: dict) -> None:
    from rich import box
    from rich.console import Console
    from rich.table import Table

    ctrl = f", controller {report['controller']}" if report.get("controller") else ""
    if report.get("ecu_arithmetic") == "fixed":
        ctrl += ", fixed-point ECU"
    table = Table(box=box.SIMPLE_HEAD,
                  title=f"{report.get('bench', {}).get('harness', 'sil').upper()}, route "
                        f"'{report['route']}', mode {report['mode']}{ctrl}, seed {report['seed']}")
    # (short headers: the table fits 80 columns; what they mean is said below it)
    for col in ("seg", "BA", "SWS", "DTD", "F N", "grade", "stored J", "drawn J", "road mm"):
        table.add_column(col, justify="right", no_wrap=True, min_width=max(5, len(col)))
    for s in report["segments"]:
        r = s["ratio"]
        if not s.get("scored", True):
            table.add_row(f"{s['grade']}@{s['speed_mps']:g}", "not scored: shorter than the "
                          "settling window", *[""] * 7)
            continue
        table.add_row(f"{s['grade']}@{s['speed_mps']:g}", f"{r['ba']:.3f}", f"{r['sws']:.3f}",
                      f"{r['dtd']:.3f}", f"{s['active']['force_rms_n']:.0f}",
                      f"{s['grade_accuracy']:.2f}", f"{s['harvested_j']:.1f}",
                      f"{s['consumed_j']:.1f}", f"{s['road_estimate_rmse_m'] * 1e3:.1f}")
    console = Console()
    console.print(table)
    console.print(
        f"seg: grade@speed (m/s). BA, SWS, DTD: ratios to the passive twin (RMS after "
        f"{report.get('settle_s', 3):g} s of each segment); F N: the force's RMS; grade: the "
        f"share of ticks with the right grade estimate; road mm: the road estimate's RMSE. "
        f"{ENERGY_COLUMNS} Grade accuracy {report['grade_accuracy']:.3f}; "
        f"{switches_phrase(report)}; trace {report['trace_sha256'][:16]}.", soft_wrap=False)
    if "verdict" in report:
        from hil.report.verdict import render

        render(report)
