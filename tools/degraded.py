"""Degraded operation measured: what each mode keeps with one sensor out (docs/degraded.md).

    python -m tools.degraded [--vehicle FILE] [--design FILE] [--seeds 1 2 3]
                             [--seconds 60] [--speed 20] [--json]

For each sensor the ECU can drive without (``firmware.diag.degrade``: body accelerometer,
wheel accelerometer, deflection sensor) and each mode on its own grade's road (energy
feedback A, comfort B, safety C, comprehensive D), SIL drives with the ECU started with that
sensor out (``firmware.ecu.Ecu.leave_out``: its channel the virtual sensor's, the filter
reduced) and, beside them, with every sensor in use, on the same seeds: the ratios to the
passive car, the energy harvested, the run's verdict. A mode is **kept** without a sensor when
on every seed its drive passes its verdict (no fail-safe, no DTC) and does what the mode does
with every sensor: no ratio more than ``MARGIN`` above that drive's, at least
``HARVEST_SHARE`` of its harvest. Every mode is allowed for the measurement;
the calibration's ``degraded_modes_*`` options say which the ECU keeps. The verdict (exit 1)
fails when the calibration keeps a mode the measurement does not (keeping fewer is allowed).
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Optional

from calib.ecu_params import degraded_modes
from calib.options import DesignOptions
from firmware.diag.degrade import SENSOR_NAMES
from firmware.params import MODE_NAMES
from hil.cli import (add_design_argument, add_json_argument, add_vehicle_argument,
                     design_or_exit, emit, positive_float, progress_bar, vehicle_or_exit)
from hil.nodes import sil
from hil.sim.road import constant_route

SENSORS = SENSOR_NAMES[:3]               # the current sensor out keeps no mode (by design)
MARGIN = 0.02          # a ratio may rise this much above the drive's with every sensor ...
HARVEST_SHARE = 0.9    # ... and energy feedback harvest this share of its energy
RUNS = (("energy", "regen", "A"), ("comfort", "comfort", "B"), ("safety", "safety", "C"),
        ("comprehensive", "comprehensive", "D"))
EXIT_DIFFERS = 1


def _why(seg: dict, ref: dict) -> list[str]:
    """How one drive with a sensor out falls short of the same seed's drive with every
    sensor (``ref``): a ratio more than MARGIN above, or less harvested than HARVEST_SHARE."""
    out = [f"{k} {v:.3f} > {ref['ratio'][k]:.3f} + {MARGIN}" for k, v in seg["ratio"].items()
           if v > ref["ratio"][k] + MARGIN]
    if seg["harvested_w"] < HARVEST_SHARE * ref["harvested_w"]:
        out.append(f"harvest {seg['harvested_w']:.2f} W < {HARVEST_SHARE} x "
                   f"{ref['harvested_w']:.2f} W")
    return out


def measure(cfg, opts: DesignOptions, seeds, seconds: float, speed: float,
            progress=None) -> dict:
    """Every sensor out (and none) x every mode x ``seeds``: the rows and the modes kept."""
    every = " ".join(m for m, _, _ in RUNS)
    allowed = dataclasses.replace(opts, **{f"degraded_modes_{s}": every for s in SENSORS})
    rows, ref, n, total = [], {}, 0, (len(SENSORS) + 1) * len(RUNS) * len(seeds)
    for out in (None,) + SENSORS:
        for name, mode, grade in RUNS:
            for seed in seeds:
                rep, _ = sil.run(cfg, constant_route(grade, speed, seconds), mode, seed,
                                 opts=allowed, leave_out=out)
                seg = rep["segments"][0]
                if out is None:
                    ref[name, seed] = seg
                why = _why(seg, ref[name, seed])
                if rep["verdict"] != "pass":
                    why.append("verdict " + ", ".join(
                        c["name"] for c in rep["checks"] if not c.get("ok", True)))
                rows.append({"sensor_out": out, "mode": name, "grade": grade, "seed": seed,
                             "ratio": seg["ratio"], "harvested_w": seg["harvested_w"],
                             "ok": not why, "why": "; ".join(why)})
                n += 1
                if progress:
                    progress(n, total)
    kept = {s: [name for name, _, _ in RUNS
                if all(r["ok"] for r in rows if r["sensor_out"] == s and r["mode"] == name)]
            for s in SENSORS}
    calibrated = {s: [m for m in MODE_NAMES[1:] if degraded_modes(
        getattr(opts, f"degraded_modes_{s}"), s) >> MODE_NAMES.index(m) & 1] for s in SENSORS}
    return {"vehicle": cfg.source, "speed_mps": speed, "seconds": seconds,
            "seeds": list(seeds), "rows": rows, "kept": kept, "calibrated": calibrated,
            "agrees": all(set(calibrated[s]) <= set(kept[s]) for s in SENSORS)}


def _render(o: dict) -> None:
    print(f"degraded operation, {o['vehicle']}: {o['seconds']:g} s at {o['speed_mps']:g} m/s,"
          f" seeds {', '.join(map(str, o['seeds']))}; ratios to passive (mean over seeds)")
    print(f"{'sensor out':14s} {'mode':14s} {'BA':>6s} {'SWS':>6s} {'DTD':>6s}  against every sensor's")
    for out in (None,) + SENSORS:
        for name, _, _ in RUNS:
            rs = [r for r in o["rows"] if r["sensor_out"] == out and r["mode"] == name]
            mean = {k: sum(r["ratio"][k] for r in rs) / len(rs) for k in ("ba", "sws", "dtd")}
            bad = [r["why"] for r in rs if not r["ok"]]
            print(f"{out or '(none)':14s} {name:14s} {mean['ba']:6.3f} {mean['sws']:6.3f} "
                  f"{mean['dtd']:6.3f}  {'met' if not bad else bad[0]}")
    for s in SENSORS:
        print(f"without {s}: kept {' '.join(o['kept'][s]) or 'none'}; calibration "
              f"{' '.join(o['calibrated'][s]) or 'none'}")
    print("the calibration keeps no mode the measurement does not" if o["agrees"] else
          "the calibration KEEPS A MODE THE MEASUREMENT DOES NOT (degraded_modes_*)")


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.degraded", description=__doc__.split(
        "\n\n")[0])
    add_vehicle_argument(ap)
    add_design_argument(ap)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--seconds", type=positive_float, default=60.0)
    ap.add_argument("--speed", type=positive_float, default=20.0)
    add_json_argument(ap)
    args = ap.parse_args(argv)
    cfg, opts = vehicle_or_exit(args.vehicle), design_or_exit(args.design) or DesignOptions()
    with progress_bar("degraded drives", not args.json) as progress:
        out = measure(cfg, opts, args.seeds, args.seconds, args.speed, progress)
    emit(out, args.json, _render)
    return 0 if out["agrees"] else EXIT_DIFFERS


if __name__ == "__main__":
    raise SystemExit(main())
