"""False alarms, measured: ``python -m hil alarms [--json]``.

Fault-free SIL drives (every shipped route, seeds 1-10, the default car and the SUV, each route
driven at 10, 20 and 30 m/s, bump stops and tyre lift-off on, the driver accepting every
recommendation so every mode is driven) and, for each, every detection of the model-based tests
(``firmware.diag.fdi``) and every DTC that failed. The goal is zero; the verdict fails on any
detection or model-based DTC. DTCs of the frame and ADC checks are listed beside it (a real
finding of the bench, such as a sensor range below what the drive reaches).
Cases run in parallel, one process per core (``--jobs``); each is deterministic.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Optional

from hil.cli import add_cache_argument
from hil.report import verdict

DEFAULT_VEHICLES = ("table3.toml", "suv.toml")
DEFAULT_SPEEDS = (10.0, 20.0, 30.0)
DEFAULT_SEEDS = 10


@dataclasses.dataclass(frozen=True)
class Case:
    route: str
    vehicle: str
    speed_mps: float
    seed: int
    duration_s: Optional[float] = None

    def command(self) -> str:
        return (f"python -m hil alarms --routes {self.route} --vehicles {self.vehicle} "
                f"--speeds {self.speed_mps:g} --seeds {self.seed}-{self.seed}"
                + (f" --duration {self.duration_s:g}" if self.duration_s else ""))


def cases(routes, vehicles, speeds, seeds, duration_s=None) -> list[Case]:
    return [Case(r, v, s, k, duration_s) for r in routes for v in vehicles for s in speeds
            for k in seeds]


def vehicle_path(name: str) -> Path:
    """A vehicle file by its path, or by the name of a shipped one (``suv.toml``)."""
    from hil.config import DEFAULT_VEHICLE_FILE

    path = Path(name)
    shipped = DEFAULT_VEHICLE_FILE.parent / name
    return shipped if not path.exists() and shipped.exists() else path


def _vehicle(name: str):
    from hil.config import load_vehicle

    cfg = load_vehicle(vehicle_path(name))
    nl = dataclasses.replace(cfg.nonlinear, bump_stops=True, tire_lift_off=True)
    return dataclasses.replace(cfg, nonlinear=nl)


def run_case(case: Case) -> dict:
    """One fault-free drive: its detections (rising edges of the model-based tests' bits:
    plausibility, supply), the ticks they were set, and the DTCs that failed."""
    import numpy as np

    from firmware import safety
    from firmware.diag import dtc
    from hil import nodes
    from hil.nodes import sil
    from hil.sim.road import load_route

    cfg = _vehicle(case.vehicle)
    r = load_route(case.route)
    route = dataclasses.replace(r, segments=tuple(
        dataclasses.replace(s, speed_mps=case.speed_mps) for s in r.segments))
    kept = {}
    make = nodes.EcuNode.summary

    def summary(self):               # (the ECU node's DTC memory, read as the run ends)
        kept["mem"] = self.state.diag.dtc
        return make(self)

    t0 = time.perf_counter()
    nodes.EcuNode.summary = summary
    try:
        report, trace = sil.run(cfg, route, "auto", case.seed, duration_s=case.duration_s)
    finally:
        nodes.EcuNode.summary = make
    model_based = safety.FAULT_PLAUSIBILITY | safety.FAULT_SUPPLY
    bits = (np.asarray(trace.arrays["faults"]) & model_based) != 0
    edges = int(np.count_nonzero(bits[1:] & ~bits[:-1]) + int(bits[:1].sum()))
    mem = kept["mem"]
    failed = [i for i, e in enumerate(mem.entries) if e.status & dtc.TFSLC]
    return {**dataclasses.asdict(case), "driven_s": len(bits) * trace.dt_s,
            "detections": edges, "plausibility_ticks": int(bits.sum()),
            "dtcs": sorted(dtc.DTCS[i].name for i in failed if dtc.DTCS[i].source == dtc.SRC_TEST),
            "other_dtcs": sorted(dtc.DTCS[i].name for i in failed
                                 if dtc.DTCS[i].source != dtc.SRC_TEST),
            "other_faults": int(np.count_nonzero(np.asarray(trace.arrays["faults"])
                                                 & ~model_based)),
            "wall_s": time.perf_counter() - t0, "command": case.command()}


def measure(todo: list[Case], jobs: int, progress=None) -> list[dict]:
    out = []
    if jobs <= 1:
        for c in todo:
            out.append(run_case(c))
            if progress:
                progress(len(out), len(todo), out[-1])
        return out
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(run_case, c) for c in todo]
        for f in as_completed(futures):
            out.append(f.result())
            if progress:
                progress(len(out), len(todo), out[-1])
    key = [dataclasses.asdict(c) for c in todo]
    return sorted(out, key=lambda r: key.index({k: r[k] for k in key[0]}))


def summarise(results: list[dict]) -> dict:
    hours = sum(r["driven_s"] for r in results) / 3600.0
    detections = sum(r["detections"] for r in results)
    dtcs = sorted({d for r in results for d in r["dtcs"]})
    other = sorted({d for r in results for d in r["other_dtcs"]})
    doc = {"cases": len(results), "hours_driven": hours, "detections": detections,
           "detections_per_hour": detections / hours if hours else float("nan"),
           "dtcs_failed": dtcs, "other_dtcs": {d: sum(d in r["other_dtcs"] for r in results)
                                               for d in other},
           "results": results,
           "worst": [r for r in sorted(results, key=lambda r: -r["detections"])
                     if r["detections"]][:10]}
    verdict.attach(doc, [verdict.check("detections", detections, "==", 0),
                         verdict.check("plausibility_dtcs_failed", len(dtcs), "==", 0)])
    return doc


def seeds_arg(text: str) -> list[int]:
    try:
        if "-" in text:
            a, b = (int(x) for x in text.split("-", 1))
        else:
            a, b = 1, int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds: N or A-B, got {text!r}") from None
    if a < 0 or b < a or b - a > 10_000:
        raise argparse.ArgumentTypeError(f"seeds: N or A-B with 0 <= A <= B, got {text!r}")
    return list(range(a, b + 1))


def _floats(text: str) -> list[float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"a comma-separated list of numbers, got {text!r}") from None
    if not all(0 < x <= 60 for x in v):
        raise argparse.ArgumentTypeError(f"speeds in (0, 60] m/s, got {text!r}")
    return v


def add_parser(sub) -> None:
    p = sub.add_parser("alarms", help="false alarms of the model-based fault detection on "
                                      "fault-free drives (goal: zero)")
    p.add_argument("--routes", help="comma-separated routes (default: every shipped one)")
    p.add_argument("--vehicles", default=",".join(DEFAULT_VEHICLES),
                   help="comma-separated vehicle files (default: %(default)s); bump stops "
                        "and tyre lift-off are switched on")
    p.add_argument("--speeds", type=_floats, default=list(DEFAULT_SPEEDS),
                   help="comma-separated speeds in m/s; every route is driven at each "
                        "(default: 10,20,30)")
    p.add_argument("--seeds", type=seeds_arg, default=list(range(1, DEFAULT_SEEDS + 1)),
                   help="N (seeds 1..N) or A-B (default: 10)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="drive only the first S seconds of each route")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="parallel processes (default: one per core)")
    p.add_argument("--out", metavar="DIR", help="write DIR/alarms.json")
    add_cache_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def main(args) -> int:
    from hil.cli import fail
    from hil.config import ConfigError
    from hil.sim.road import load_route, shipped_routes

    routes = args.routes.split(",") if args.routes else shipped_routes()
    vehicles = args.vehicles.split(",")
    try:
        for r in routes:
            load_route(r)
        for v in vehicles:
            _vehicle(v)
    except ConfigError as exc:
        fail(str(exc))
    if args.jobs < 1:
        fail("--jobs must be at least 1")
    todo = cases(routes, vehicles, args.speeds, args.seeds, args.duration)
    start = time.monotonic()

    def progress(done, total, r):
        eta = (time.monotonic() - start) / done * (total - done)
        print(f"alarms: {done}/{total}  {r['route']} {r['vehicle']} {r['speed_mps']:g} m/s "
              f"seed {r['seed']}: {r['detections']} detections  (eta {eta:.0f} s)",
              file=sys.stderr, flush=True)

    doc = summarise(measure(todo, min(args.jobs, len(todo)), progress))
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "alarms.json").write_text(json.dumps(doc, indent=1) + "\n")
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        print(f"{doc['cases']} fault-free drives, {doc['hours_driven']:.2f} h driven: "
              f"{doc['detections']} detections ({doc['detections_per_hour']:.3g} per hour); "
              f"model-based DTCs failed: {', '.join(doc['dtcs_failed']) or 'none'}")
        for r in doc["worst"]:
            print(f"  {r['detections']} detections: {r['command']}")
        for name, n in doc["other_dtcs"].items():    # (the frame and ADC checks' findings)
            where = next(r["command"] for r in doc["results"] if name in r["other_dtcs"])
            print(f"  also failed (not model-based): {name} in {n} drive(s), e.g. {where}")
        print(f"verdict: {doc['verdict']}")
    return 0 if doc["verdict"] == "pass" else 1
