"""Which single sensor faults the isolation bank can tell apart, and how fast: the CLI of the
analysis ``calib.isolability`` (docs/diagnostics.md, "Isolability").

    python -m tools.isolability [--vehicle FILE] [--grade B] [--speed 20] [--json OUT]

Writes the per-fault table as Markdown. Exit 0 when the analysis's self-checks hold, 1 when one
fails, 2 on bad input.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from calib import fdi_bank as fb
from calib.isolability import analyse, counts
from calib.options import DesignOptions


def _cell(v) -> str:
    return "–" if v is None else f"{v:g}"


def render(res: dict, vehicle: str) -> str:
    """The analysis as Markdown: per condition a table of every fault, then the counts."""
    out = [f"# Isolability: {vehicle}, grade {res['grade']} at {res['speed_mps']:g} m/s",
           "", f"False-alarm rate {res['alpha']:g} per window; the ECU's tests W = "
           f"{res['window']} ticks; the bank: {res['bank']}.", "",
           "Filters (blind to: reads): " + "; ".join(
               f"{k}: {', '.join(v)}" for k, v in res["filters"].items()), ""]
    for cond, info in res["conditions"].items():
        rows = [r for r in res["faults"] if r["condition"] == cond]
        out += [f"## {cond} (force RMS {info['force_rms_n']:.0f} N)", "",
                "| sensor | fault | size | ECU tests ms | bank ms | isolated ms | "
                "candidates left |", "|---|---|---|---|---|---|---|"]
        for r in rows:
            size = "–" if r["size"] is None else f"{r['magnitude']} ({r['size']:.3g})" \
                if r["magnitude"] != "-" else "–"
            cand = ", ".join(r.get("candidates", [])) if not r.get("isolable") else ""
            out.append(f"| {r['sensor']} | {r['kind']} | {size} | {_cell(r.get('detect_ms'))} | "
                       f"{_cell(r.get('bank_detect_ms'))} | {_cell(r.get('isolated_ms'))} | "
                       f"{r.get('note', cand)} |")
        c = counts(rows)
        out += ["", f"Detected {c['detected']} of {c['faults']}, isolated {c['isolated']} "
                f"({c['isolated'] / c['faults']:.0%}); large, bias and stuck faults isolated "
                f"{c['key_isolated']} of {c['key']}.", ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    from calib.errors import ConfigError
    from calib.iso8608 import GRADE_GQ_M3
    from hil.config import default_vehicle, load_vehicle

    ap = argparse.ArgumentParser(prog="python -m tools.isolability", description=__doc__.split(
        "\n\n")[0])
    ap.add_argument("--vehicle", help="vehicle TOML (default: Table 3's car)")
    ap.add_argument("--grade", default="B", help="the road's ISO 8608 grade (default B)")
    ap.add_argument("--speed", type=float, default=20.0, help="m/s (default 20)")
    d = DesignOptions()
    ap.add_argument("--structure", default=d.fdi_bank_structure, choices=("voltage", "force"),
                    help="the bank's structure (DesignOptions.fdi_bank_structure)")
    ap.add_argument("--walk", type=float, default=d.fdi_bank_offset_walk_v,
                    help="the winding model's voltage offset walk, V/sqrt(s)")
    ap.add_argument("--window", type=int, default=d.fdi_bank_window,
                    help="the bank's EWMA window, ticks")
    ap.add_argument("--out", help="write the Markdown report here (default: stdout)")
    ap.add_argument("--json", help="write the results as JSON here")
    a = ap.parse_args(argv)
    if a.grade not in GRADE_GQ_M3 or not 0.5 <= a.speed <= 70.0:
        print(f"isolability: grade must be one of {''.join(GRADE_GQ_M3)} and speed within "
              f"0.5-70 m/s, got {a.grade!r}, {a.speed}", file=sys.stderr)
        return 2
    try:
        cfg = load_vehicle(a.vehicle) if a.vehicle else default_vehicle()
        opts = dataclasses.replace(DesignOptions(), fdi_bank_structure=a.structure,
                                   fdi_bank_offset_walk_v=a.walk, fdi_bank_window=a.window)
        fb.check_options(opts)
    except (ConfigError, ValueError) as e:
        print(f"isolability: {e}", file=sys.stderr)
        return 2
    n = [0]

    def progress(row):
        n[0] += 1
        print(f"\r{n[0]} faults analysed ({row['condition']}, {row['sensor']} {row['kind']})"
              + " " * 10, end="", file=sys.stderr, flush=True)
    try:
        res = analyse(cfg, opts, a.grade, a.speed, progress)
    except AssertionError as e:              # a self-check of the analysis failed
        print(f"\nisolability: FAIL: {e}", file=sys.stderr)
        return 1
    print(file=sys.stderr)
    text = render(res, a.vehicle or "table3.toml")
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text + "\n")
    else:
        print(text)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1, sort_keys=True)
    c = [counts([r for r in res["faults"] if r["condition"] == cond])
         for cond in res["conditions"]]
    print("isolability: PASS (self-checks held): " + "; ".join(
        f"{cond} {x['isolated']}/{x['faults']} isolated" for cond, x in zip(res["conditions"], c)),
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
