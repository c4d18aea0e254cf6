"""The shipped calibrations as data (``calib.dataset``): design each shipped vehicle afresh and
write its data file, or compare it with the committed one.

    python -m tools.calibration [--check] [--tolerance REL] [--json]
    python -m tools.calibration --campaign FILE [--json]

Each vehicle file of ``hil/vehicles/`` (default design options, its shipped gains file) is
designed afresh (never from its data file; from the design cache where an entry is there, which
``SUSPENSION_NO_CACHE=1`` turns off) and written to ``calib/data/<vehicle>.json`` where it
differs. ``--check`` writes nothing: it lists every value of the fresh design that differs
from the committed one (its path in the calibration, element, both values and the change
relative to the largest magnitude of its array) and exits 1 when a data file is missing or
stale (other design inputs) or a value moved by more than ``--tolerance`` (default 1e-9:
ten times the calibration's grid, ``calib.grid``); ``identical`` in ``--json`` says whether
the calibration images are the same bytes.

``--campaign FILE`` designs each calibration car of a campaign as its driver does
(``hil.validate.campaign.design``, one per ``calibration_key``) and lists the SHA-256 of each
image: two hosts (or two ``OPENBLAS_CORETYPE``s) compare theirs line by line.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from calib import dataset
from hil.cli import add_json_argument, emit, fail

ROOT = Path(__file__).resolve().parents[1]
VEHICLES = ROOT / "hil" / "vehicles"
TOLERANCE = 1e-9


def shipped() -> list[Path]:
    return sorted(VEHICLES.glob("*.toml"))


def leaves(obj, path: str = ""):
    """(path, value) of every number and array of a calibration tree."""
    import dataclasses

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            yield from leaves(getattr(obj, f.name), f"{path}.{f.name}" if path else f.name)
    elif isinstance(obj, tuple) and obj and dataclasses.is_dataclass(obj[0]):
        for i, v in enumerate(obj):
            yield from leaves(v, f"{path}[{i}]")
    else:
        yield path, obj


def moved(old, new) -> list[dict]:
    """Every value of ``new`` that differs from ``old`` (bit for bit: -0 is not +0): path,
    flat index (None for a scalar), both values and the change relative to the largest
    magnitude of its array (inf where a value is not a number or the shapes differ)."""
    out = []
    a_leaves, b_leaves = dict(leaves(old)), dict(leaves(new))
    for path in sorted(set(a_leaves) | set(b_leaves)):
        a, b = a_leaves.get(path), b_leaves.get(path)
        a_arr, b_arr = np.asarray(a), np.asarray(b)
        if a_arr.shape != b_arr.shape or not {a_arr.dtype.kind, b_arr.dtype.kind} <= set("fiub"):
            if a_arr.shape != b_arr.shape or not np.array_equal(a_arr, b_arr):
                out.append({"path": path, "index": None, "committed": str(a), "fresh": str(b),
                            "change": float("inf")})
            continue
        af, bf = a_arr.astype(float).ravel(), b_arr.astype(float).ravel()
        scale = float(np.max(np.abs(af))) if af.size else 0.0
        same = ((af == bf) & (np.signbit(af) == np.signbit(bf))) | (np.isnan(af) & np.isnan(bf))
        for i in np.flatnonzero(~same):
            out.append({"path": path, "index": int(i) if a_arr.ndim else None,
                        "committed": a_arr.ravel()[i].item(), "fresh": b_arr.ravel()[i].item(),
                        "change": _change(af[i], bf[i], scale)})
    return out


def _change(a: float, b: float, scale: float) -> float:
    if not (np.isfinite(a) and np.isfinite(b)):
        return float("inf")
    return abs(float(b) - float(a)) / scale if scale > 0 else float("inf")


def design(path: Path):
    """(the fresh calibration of the shipped vehicle file, its design key)."""
    from calib.ecu_params import build, design_key
    from calib.options import DesignOptions
    from hil.config import load_vehicle

    cfg = load_vehicle(path)
    opts = DesignOptions()
    return build(cfg, opts), design_key(cfg, None, opts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.calibration",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if a committed calibration is missing, stale "
                         "or a value moved by more than --tolerance")
    ap.add_argument("--tolerance", type=float, default=TOLERANCE, metavar="REL",
                    help=f"largest change, relative to its array's largest magnitude "
                         f"(default {TOLERANCE:g})")
    ap.add_argument("--campaign", metavar="FILE",
                    help="list the design hash of each calibration car of this campaign")
    add_json_argument(ap)
    args = ap.parse_args(argv)
    if not (args.tolerance >= 0.0):
        fail(f"--tolerance must be a number >= 0, got {args.tolerance}")
    if args.campaign:
        return campaign_designs(args.campaign, args.json)
    os.environ[dataset.ENV_OFF] = "1"           # (a fresh design, never the data it checks)
    from calib.errors import ConfigError

    rows, bad = [], False
    for path in shipped():
        try:
            p, key = design(path)
        except ConfigError as exc:
            fail(str(exc))
        out = dataset.path_for(path.name)
        row = {"vehicle": path.name, "file": str(out.relative_to(ROOT)),
               "image_sha256": dataset.image_sha256(p), "moved": []}
        text = dataset.text(p, path.name, key)
        old = None
        if out.is_file():
            try:
                old = dataset.read(out)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                row["error"] = f"unreadable: {exc}"
        if old is None:
            row["state"] = "missing" if "error" not in row else "unreadable"
        else:
            row["moved"] = moved(old["params"], p)
        if old is not None and old.get("design_key") != key:
            row["state"] = "stale"
        elif old is not None:
            row["state"] = ("identical" if old.get("image_sha256") == row["image_sha256"]
                            and not row["moved"] else
                            "within" if all(m["change"] <= args.tolerance for m in row["moved"])
                            else "differs")
        bad |= row["state"] not in ("identical", "within")
        if not args.check and row["state"] != "identical":
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(text)
            row["written"] = True
        rows.append(row)
    result = {"vehicles": rows, "tolerance": args.tolerance,
              "identical": all(r["state"] == "identical" for r in rows)}
    emit(result, args.json, _render)
    return 1 if args.check and bad else 0


def campaign_designs(path: str, as_json: bool) -> int:
    """Each calibration car's design hash; exit 1 when a car has no calibration."""
    from calib.errors import ConfigError
    from hil.validate import campaign

    try:
        camp = campaign.load(path)
    except ConfigError as exc:
        fail(str(exc))
    cars: dict[str, dict] = {}
    for case in camp.cases:
        key = campaign.calibration_key(case)
        if key in cars:
            continue
        p = campaign.design(case)
        cars[key] = {"car": campaign.spec.label(case["vehicle"]), "noise": case["noise"],
                     "design_sha256": dataset.image_sha256(p) if not isinstance(p, str) else "",
                     "error": p if isinstance(p, str) else None}
    rows = list(cars.values())
    emit({"campaign": camp.name, "cars": rows}, as_json,
         lambda r: [print(f"{c['design_sha256'] or 'no calibration: ' + c['error']}  "
                          f"{c['car']} (noise x{c['noise']:g})") for c in r["cars"]])
    return 1 if any(c["error"] for c in rows) else 0


def _render(result: dict) -> None:
    for r in result["vehicles"]:
        what = {"identical": "the same bytes as the committed calibration",
                "within": f"{len(r['moved'])} value(s) moved, all within "
                          f"{result['tolerance']:g}",
                "differs": f"{len(r['moved'])} value(s) moved, "
                           f"{sum(m['change'] > result['tolerance'] for m in r['moved'])} "
                           f"beyond {result['tolerance']:g}",
                "stale": "committed for other design inputs (the vehicle, the options, the "
                         "gains file or the generator's version changed)",
                "missing": "no committed calibration",
                "unreadable": r.get("error", "unreadable")}[r["state"]]
        verb = " (written)" if r.get("written") else ""
        print(f"{r['file']}: {r['vehicle']}: {what}{verb}")
        for m in r["moved"][:40]:
            where = m["path"] + (f"[{m['index']}]" if m["index"] is not None else "")
            print(f"  {where}: {m['committed']!r} -> {m['fresh']!r} (change {m['change']:.3g})")
        if len(r["moved"]) > 40:
            print(f"  ... and {len(r['moved']) - 40} more (--json lists them all)")


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
