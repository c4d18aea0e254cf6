"""Validation campaigns: a matrix of SIL cases (routes x seeds x vehicles x modes x arithmetic
x sensor noise) run on Dask, each judged, the results in SQLite.

    python -m hil campaign FILE.toml [--scheduler local|tcp://HOST:PORT] [--workers N]
                                     [--out DIR] [--json]
    python -m hil campaign-report DIR/campaign.sqlite [--out DIR] [--json]

A case is one ``hil sim`` run, deterministic: the same case gives the same ``trace_sha256``
on any worker and as the plain ``hil sim`` command stored with it. Workers get the project's
code from the installed package and the vehicle and route files as text inside the case (no
shared disk). Results go to ``DIR/campaign.sqlite`` (schema: ``SCHEMA``) as each case ends;
a case already there is not run again (resumable; Ctrl-C keeps what finished).

The campaign file (every key but ``routes`` optional)::

    [campaign]
    name = "family"
    routes = ["full_road_section"]          # shipped names or route files
    seeds = [1, 2, 3]                       # or {from = 1, to = 10}
    modes = ["auto"]
    fixed_point = [false]                   # [false, true]: both arithmetic paths
    noise = [1.0]                           # factors on every sensor's noise
    duration_s = 60                         # stop each run early (default: the whole route)

    [[vehicle]]                             # none: the default car
    file = "hil/vehicles/suv.toml"          # omit for the default car
    sprung_mass_kg = [0.8, 1.0, 1.2]        # variants: factors on keys of [vehicle]

    [nonlinear]                             # every vehicle's [nonlinear] keys set to these
    bump_stops = true                       # (a vehicle file's own table, then this one)

    [criteria]
    acceptance = true                       # the firmware issue's SIL acceptance per segment;
                                            # "relative": BA, DTD bounds moved by the
                                            # vehicle's limit minus the default car's
    max_gap = 0.03                          # each mean ratio at most this above its limit
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import json
import math
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any, Iterable, Optional

from calib.errors import ConfigError
from hil.config import PACKAGE_DIR
from hil.validate.acceptance import GRADE_MODE, RELATIVE_KEY, violations

VEHICLE_KEYS = ("sprung_mass_kg", "unsprung_mass_kg", "spring_stiffness_n_per_m",
                "damping_n_s_per_m", "tire_stiffness_n_per_m")
MIXED = "mixed"            # a segment driven in more than one mode (campaign._driven)
DRIVEN_SHARE = 0.95        # ... for less than this share of its window in its main mode

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS cases (
    case_id TEXT PRIMARY KEY,      -- SHA-256 of the case's canonical JSON (first 16 hex)
    campaign TEXT NOT NULL,
    route TEXT NOT NULL, seed INTEGER NOT NULL, vehicle TEXT NOT NULL, factors TEXT NOT NULL,
    mode TEXT NOT NULL, fixed_point INTEGER NOT NULL, noise REAL NOT NULL, duration_s REAL,
    software_version TEXT NOT NULL, calibration_sha256 TEXT NOT NULL,
    trace_sha256 TEXT NOT NULL, verdict TEXT NOT NULL, failed TEXT NOT NULL,
    wall_s REAL NOT NULL, worker TEXT NOT NULL, command TEXT NOT NULL, case_json TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS segments (
    case_id TEXT NOT NULL REFERENCES cases(case_id), idx INTEGER NOT NULL,
    grade TEXT NOT NULL, speed_mps REAL NOT NULL, mode TEXT NOT NULL, scored INTEGER NOT NULL,
    ba_ratio REAL, sws_ratio REAL, dtd_ratio REAL,
    limit_name TEXT, limit_value REAL, gap REAL, ok INTEGER NOT NULL,
    metrics TEXT NOT NULL,         -- the segment's whole hil sim JSON
    PRIMARY KEY (case_id, idx)
);
"""


# ------------------------------------------------------------------ the campaign file
@dataclasses.dataclass(frozen=True)
class Campaign:
    name: str
    cases: tuple[dict, ...]
    acceptance: bool | str          # True, False or "relative"
    max_gap: Optional[float]


def load(path: str | Path) -> Campaign:
    """Read and expand a campaign file; ConfigError (one line) on anything wrong."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    for key in data:
        if key not in ("campaign", "vehicle", "criteria", "nonlinear"):
            raise ConfigError(f"{path}: unknown table '{key}' (campaign, vehicle, criteria, "
                              "nonlinear)")
    c = data.get("campaign")
    if not isinstance(c, dict):
        raise ConfigError(f"{path}: missing table [campaign]")
    known = ("name", "routes", "seeds", "modes", "fixed_point", "noise", "duration_s")
    for key in c:
        if key not in known:
            raise ConfigError(f"{path}: unknown key 'campaign.{key}' ({', '.join(known)})")
    routes = [_route_spec(path, r) for r in _list(path, c, "routes", str, required=True)]
    seeds = _seeds(path, c.get("seeds", [1]))
    modes = _list(path, c, "modes", str, default=["auto"])
    from hil.config import MODE_CHOICES

    for m in modes:
        if m not in MODE_CHOICES:
            raise ConfigError(f"{path}: campaign.modes: {m!r} is not one of "
                              f"{', '.join(MODE_CHOICES)}")
    fixed = _list(path, c, "fixed_point", bool, default=[False])
    noise = [float(x) for x in _list(path, c, "noise", (int, float), default=[1.0])]
    if any(not (math.isfinite(x) and 0 <= x <= 100) for x in noise):
        raise ConfigError(f"{path}: campaign.noise: factors in [0, 100]")
    duration = c.get("duration_s")
    if duration is not None and not (isinstance(duration, (int, float))
                                     and math.isfinite(duration) and duration > 0):
        raise ConfigError(f"{path}: campaign.duration_s must be a positive number")
    nonlinear = _nonlinear(path, data.get("nonlinear"))
    vehicles = [v for t in (data.get("vehicle") or [{}]) for v in _vehicles(path, t, nonlinear)]
    crit = data.get("criteria", {})
    max_gap = crit.get("max_gap")
    if max_gap is not None and not (isinstance(max_gap, (int, float)) and max_gap >= 0):
        raise ConfigError(f"{path}: criteria.max_gap must be a number >= 0")
    acceptance = crit.get("acceptance", True)
    if not isinstance(acceptance, bool) and acceptance != "relative":
        raise ConfigError(f"{path}: criteria.acceptance must be true, false or \"relative\"")
    cases = {}                           # (a case listed twice is one case)
    for r, s, v, m, f, n in itertools.product(routes, seeds, vehicles, modes, fixed, noise):
        case = {"route": r, "seed": s, "vehicle": v, "mode": m, "fixed_point": f, "noise": n,
                "duration_s": duration}
        cases.setdefault(case_id(case), case)
    cases = tuple(cases.values())
    return Campaign(str(c.get("name", path.stem)), cases, acceptance,
                    None if max_gap is None else float(max_gap))


def _list(path, table, key, kind, default=None, required=False) -> list:
    if key not in table:
        if required:
            raise ConfigError(f"{path}: missing key 'campaign.{key}'")
        return list(default)
    value = table[key]
    if not isinstance(value, list):
        value = [value]
    if not value or not all(isinstance(x, kind) and not (kind is not bool and
                                                          isinstance(x, bool)) for x in value):
        raise ConfigError(f"{path}: campaign.{key}: a non-empty list of the right type")
    return value


def _seeds(path, value) -> list[int]:
    if isinstance(value, dict):
        lo, hi = value.get("from"), value.get("to")
        if not (isinstance(lo, int) and isinstance(hi, int) and 0 <= lo <= hi):
            raise ConfigError(f"{path}: campaign.seeds: {{from = N, to = M}} with 0 <= N <= M")
        return list(range(lo, hi + 1))
    if not isinstance(value, list):
        value = [value]
    if not value or not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0
                            for x in value):
        raise ConfigError(f"{path}: campaign.seeds: a list of integers >= 0")
    return value


def _route_spec(path: Path, r: str) -> dict:
    """A shipped route by name, or a route file's text (the worker needs no disk)."""
    from hil.sim.road import load_route

    p = (path.parent / r) if not Path(r).is_absolute() else Path(r)
    if r.endswith(".toml"):
        if not p.is_file():
            p = Path(r)
        try:
            load_route(str(p))
        except (ConfigError, OSError, ValueError) as exc:
            raise ConfigError(f"{path}: route {r}: {exc}") from None
        return {"name": p.stem, "toml": p.read_text()}
    try:
        load_route(r)
    except (ConfigError, ValueError) as exc:
        raise ConfigError(f"{path}: route {r}: {exc}") from None
    return {"name": r}


def _nonlinear(path: Path, table) -> dict:
    """The campaign's [nonlinear] table: keys of a vehicle file's [nonlinear], set on every
    vehicle (checked here by the vehicle file's own reader, on the default car: unknown keys,
    types and ranges, in one line)."""
    if table is None:
        return {}
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [nonlinear] must be a table")
    vehicle_config({"name": "default", "toml": None, "factors": {}, "nonlinear": table}, 1.0,
                   f"{path}: ")
    return dict(table)


def _vehicles(path: Path, table: dict, nonlinear: dict) -> list[dict]:
    """A [[vehicle]] table: its file as text (none: the default car) and each combination of
    its factor lists; ``nonlinear``: the campaign's [nonlinear] keys, on each."""
    from hil.config import load_vehicle

    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [[vehicle]] must be a table")
    file = table.get("file")
    text, name = None, "default"
    if file is not None:
        p = path.parent / file if (path.parent / file).is_file() else Path(file)
        load_vehicle(p)                          # (its own errors, one line)
        text, name = p.read_text(), p.stem
    for key in table:
        if key != "file" and key not in VEHICLE_KEYS:
            raise ConfigError(f"{path}: vehicle key '{key}': file or one of "
                              f"{', '.join(VEHICLE_KEYS)}")
    axes = []
    for key in VEHICLE_KEYS:
        if key in table:
            vals = table[key] if isinstance(table[key], list) else [table[key]]
            if not vals or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                   and 0 < x < 10 for x in vals):
                raise ConfigError(f"{path}: vehicle.{key}: factors in (0, 10)")
            axes.append([(key, float(x)) for x in vals])
    out = []
    for combo in itertools.product(*axes) if axes else [()]:
        factors = {k: v for k, v in combo if v != 1.0}
        spec = {"name": name, "toml": text, "factors": factors}
        if nonlinear:                     # (absent when empty: earlier cases keep their ids)
            spec["nonlinear"] = nonlinear
        if factors:                       # a variant the bench cannot simulate: said now
            from calib.model import check_plausible

            check_plausible(vehicle_config(spec, 1.0), f"{path}: vehicle {_label(spec)}")
        out.append(spec)
    return out


def _label(spec: dict) -> str:
    return spec["name"] + "".join(f" {k}x{v:g}" for k, v in sorted(spec["factors"].items()))


# ------------------------------------------------------------------ one case
def case_id(case: dict) -> str:
    return hashlib.sha256(json.dumps(case, sort_keys=True).encode()).hexdigest()[:16]


def vehicle_config(spec: dict, noise: float, where: str = ""):
    """The case's vehicle: its file (or the default car), the factors on [vehicle], the
    campaign's [nonlinear] keys, the noise factor on every sensor."""
    from hil.config import DEFAULT_VEHICLE_FILE, default_vehicle

    from calib.vehicle import parse_vehicle
    base = default_vehicle()
    data = tomllib.loads(spec["toml"] or DEFAULT_VEHICLE_FILE.read_text())
    for key, factor in spec["factors"].items():
        data["vehicle"][key] = data["vehicle"][key] * factor
    if spec.get("nonlinear"):
        data["nonlinear"] = {**data.get("nonlinear", {}), **spec["nonlinear"]}
    cfg = parse_vehicle(data, Path(f"{where}<{_label(spec)}>"), None if not spec["toml"] else base)
    if noise != 1.0:
        sensors = {f.name: dataclasses.replace(getattr(cfg.sensors, f.name),
                                               noise_std=getattr(cfg.sensors, f.name).noise_std
                                               * noise)
                   for f in dataclasses.fields(cfg.sensors)}
        cfg = dataclasses.replace(cfg, sensors=type(cfg.sensors)(**sensors))
    return cfg


def route_of(spec: dict):
    from hil.sim.road import load_route, parse_route

    if "toml" in spec:
        return parse_route(tomllib.loads(spec["toml"]), Path(f"<{spec['name']}>"), spec["name"])
    return load_route(spec["name"])


def command(case: dict, db_path: str = "DB") -> str:
    """The hil sim command that reproduces a case (vehicle variants and noise factors have no
    command-line form: ``hil campaign-case DB CASE_ID`` runs the case the database holds)."""
    parts = ["python -m hil sim", f"--route {case['route']['name']}",
             f"--mode {case['mode']}", f"--seed {case['seed']}"]
    v = case["vehicle"]
    shipped = PACKAGE_DIR / "vehicles" / f"{v['name']}.toml"
    if v["toml"]:
        if not (shipped.is_file() and shipped.read_text() == v["toml"]):
            return f"python -m hil campaign-case {db_path} {case_id(case)}"
        parts.append(f"--vehicle hil/vehicles/{v['name']}.toml")
    if "toml" in case["route"]:               # a route file: its text is in the case
        return f"python -m hil campaign-case {db_path} {case_id(case)}"
    if case["fixed_point"]:
        parts.append("--fixed-point")
    if case["duration_s"] is not None:
        parts.append(f"--duration {case['duration_s']:g}")
    if v["factors"] or v.get("nonlinear") or case["noise"] != 1.0:
        return f"python -m hil campaign-case {db_path} {case_id(case)}"
    return " ".join(parts + ["--key-file KEY"])


# what defines the program a case runs, beside its inputs: the packages' sources and data
SOURCE_PACKAGES = ("firmware", "calib", "hil")
SOURCE_SUFFIXES = (".py", ".toml", ".json")


@functools.lru_cache(maxsize=1)
def source_sha256() -> str:
    """SHA-256 over the source and data files of the firmware, calib and hil packages and the
    DBC, each by its path in the project: two processes with the same digest run the same
    program (the ``software_version`` of a case says which)."""
    import importlib

    from hil.transport.codec import DBC_PATH

    files = []
    for name in SOURCE_PACKAGES:
        base = Path(importlib.import_module(name).__file__).resolve().parent
        files += [(f"{name}/{f.relative_to(base).as_posix()}", f) for f in base.rglob("*")
                  if f.suffix in SOURCE_SUFFIXES and "__pycache__" not in f.parts
                  and f.is_file()]
    files.append(("dbc/" + DBC_PATH.name, DBC_PATH))
    h = hashlib.sha256()
    for rel, f in sorted(files):
        data = f.read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode())
        h.update(data)
    return h.hexdigest()


def software_version() -> str:
    """The ECU's software version (DID 0xF195) and the digest of the code that ran it:
    ``suspension-0.1.0+src.1a2b3c4d5e6f``."""
    from calib.ecu_params import SOFTWARE_VERSION

    return f"{SOFTWARE_VERSION}+src.{source_sha256()[:12]}"


# the SecOC key of every case: fixed (public, like the golden runs'), so a case's bytes are
# the same everywhere; the trace hash does not depend on it
CASE_KEY = bytes(range(16))


def run_case(case: dict, acceptance: bool | str = True) -> dict:
    """Run one case (on a worker): the row of ``cases`` and the rows of ``segments``. A case
    that raises is a result too (verdict ``error``, the exception in ``failed``): one bad
    case does not stop a campaign."""
    t0 = time.perf_counter()
    try:
        return _run_case(case, acceptance, t0)
    except Exception as exc:  # noqa: BLE001 - recorded with the case
        return {"case_id": case_id(case), "case": case, "calibration_sha256": "",
                "software_version": _version_or_blank(), "trace_sha256": "",
                "verdict": "error",
                "failed": [f"{type(exc).__name__}: {exc}"],
                "wall_s": time.perf_counter() - t0,
                "worker": f"{socket.gethostname()}:{os.getpid()}", "segments": []}


def _version_or_blank() -> str:
    try:
        return software_version()
    except Exception:  # noqa: BLE001 - an error row without a version rather than none
        return ""


def _run_case(case: dict, acceptance: bool | str, t0: float) -> dict:
    from hil.nodes import sil

    cfg = vehicle_config(case["vehicle"], case["noise"])
    route = route_of(case["route"])
    params = sil.ecu_params(cfg, case["mode"])
    report, _ = sil.run(cfg, route, case["mode"], case["seed"], params=params,
                        duration_s=case["duration_s"], fixed_point=case["fixed_point"],
                        key=CASE_KEY)
    failed = [c["name"] for c in report["checks"] if not c["ok"]]
    segments = []
    for i, (seg, rs) in enumerate(zip(report["segments"], route.segments)):
        row = _judge(cfg, route, rs, seg, case["mode"], acceptance)
        row["idx"] = i
        if not row["ok"]:
            failed.append(f"segment {i + 1} ({seg['grade']}@{seg['speed_mps']:g}): "
                          f"{row['why']}")
        segments.append(row)
    return {"case_id": case_id(case), "case": case,
            "calibration_sha256": bytes(params.calibration_sha256).hex(),
            "software_version": software_version(),
            "trace_sha256": report["trace_sha256"],
            "verdict": "fail" if failed else "pass", "failed": failed,
            "wall_s": time.perf_counter() - t0,
            "worker": f"{socket.gethostname()}:{os.getpid()}", "segments": segments}


def _judge(cfg, route, rs, seg: dict, mode: str, acceptance: bool | str) -> dict:
    """A segment against the acceptance of the mode it was driven in, and its gap to the
    vehicle's own limit for that mode (``calib.linear.physical_limits``: no controller can go
    below it). The gap is judged on the mean over the seeds, in ``report``: one segment's
    ratio scatters around the mean by more than the 0.03 a design is held to."""
    driven = _driven(seg, mode)
    row = {"grade": seg["grade"], "speed_mps": seg["speed_mps"], "mode": driven,
           "scored": bool(seg.get("scored", True)), "ratio": seg.get("ratio", {}),
           "limit_name": None, "limit_value": None, "gap": None, "ok": True, "why": "",
           "metrics": seg}
    if not row["scored"] or driven not in ("comfort", "safety", "comprehensive"):
        return row
    limits = _limits(cfg.vehicle, rs, route)
    r = seg["ratio"]
    name, value = {"comfort": ("comfort_ba", r["ba"]), "safety": ("safety_dtd", r["dtd"]),
                   "comprehensive": ("eq43_sum", sum(r.values()))}[driven]
    limit = limits[{"comfort": "comfort", "safety": "safety",
                    "comprehensive": "eq43"}[driven]]
    row.update(limit_name=name, limit_value=limit, gap=value - limit)
    why = []
    if acceptance:
        raised = None
        if acceptance == "relative" and driven in RELATIVE_KEY:
            # the same margin above this vehicle's limit as above the default car's
            from hil.config import default_vehicle

            raised = {RELATIVE_KEY[driven]: limit - _limits(default_vehicle().vehicle, rs,
                                                            route)[driven]}
        why = violations(driven, r, limit, raised)
    row["ok"], row["why"] = not why, "; ".join(why)
    return row


def _driven(seg: dict, mode: str) -> str:
    """The mode a segment was driven in: the active mode of at least ``DRIVEN_SHARE`` of its
    scored window, else ``MIXED``: the road-holding override took over for a longer part of
    it (safety first, ``road_holding_share``), or the driver's mode changed inside it. A
    mixed window's ratios belong to no mode, so no mode's acceptance or limit judges them;
    the report counts them. (A few per cent in another mode are judged with the window's
    mode: the override's safety mode has a higher BA ratio and Eq. (43) sum than comfort and
    comprehensive, so that judgement errs on the strict side.)"""
    modes = seg.get("modes")
    if not modes:                     # (not scored)
        return GRADE_MODE.get(seg["grade"], mode) if mode == "auto" else mode
    top, share = max(modes.items(), key=lambda kv: kv[1])
    return top if share >= DRIVEN_SHARE else MIXED


def _limits(vehicle, rs, route) -> dict:
    """The limits (``calib.linear.physical_limits``) of a vehicle on a route segment's road."""
    return _limit_values(vehicle, rs.gq_m3, rs.speed_mps, route.road.convention,
                         route.road.cutoff_n_per_m)


@functools.lru_cache(maxsize=64)
def _limit_values(vehicle, gq: float, speed: float, convention: str, cutoff: float) -> dict:
    """The limits' values, kept in the design cache (``calib.cache``: keyed by the vehicle,
    the road and the design code; shared by a campaign's workers, which would otherwise each
    solve them for every vehicle: a second or two of Riccati solves per segment, more than a
    case's drive)."""
    import pickle

    from calib import cache
    from calib.linear import physical_limits
    from calib.model import linear_model

    def compute() -> dict:
        res = physical_limits(linear_model(vehicle, gq, speed, convention, cutoff))
        return {name: r.value for name, r in res.items()}
    parts = (pickle.dumps(vehicle, protocol=5), repr((gq, speed, convention, cutoff)).encode())
    return cache.cached("limits", parts, compute)


# ------------------------------------------------------------------ the database
def open_db(path: Path) -> sqlite3.Connection:
    path.parent.mkdir(parents=True, exist_ok=True)
    db = sqlite3.connect(str(path))
    db.executescript(SCHEMA)
    return db


def done_ids(db: sqlite3.Connection) -> set[str]:
    return {r[0] for r in db.execute("SELECT case_id FROM cases")}


def store(db: sqlite3.Connection, campaign: str, res: dict, db_path: str = "DB") -> None:
    """One finished case, in one transaction (a case is in the database whole or not)."""
    c = res["case"]
    with db:
        db.execute("INSERT OR IGNORE INTO cases VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                   (res["case_id"], campaign, c["route"]["name"], c["seed"],
                    c["vehicle"]["name"], json.dumps(c["vehicle"]["factors"], sort_keys=True),
                    c["mode"], int(c["fixed_point"]), c["noise"], c["duration_s"],
                    res["software_version"], res["calibration_sha256"], res["trace_sha256"],
                    res["verdict"], json.dumps(res["failed"]), res["wall_s"], res["worker"],
                    command(c, db_path), json.dumps(c, sort_keys=True)))
        for s in res["segments"]:
            r = s["ratio"]
            db.execute("INSERT OR IGNORE INTO segments VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                       (res["case_id"], s["idx"], s["grade"], s["speed_mps"], s["mode"],
                        int(s["scored"]), r.get("ba"), r.get("sws"), r.get("dtd"),
                        s["limit_name"], s["limit_value"], s["gap"], int(s["ok"]),
                        json.dumps(_finite(s["metrics"]), sort_keys=True)))


def _finite(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x


# ------------------------------------------------------------------ running on Dask
def run(campaign: Campaign, db_path: Path, scheduler: str = "local",
        workers: Optional[int] = None, progress=None) -> dict:
    """Run the cases not yet in the database on Dask; store each as it ends. Returns
    {"run": n, "skipped": n, "failed": n}."""
    from dask.distributed import Client, LocalCluster, as_completed

    db = open_db(db_path)
    with db:
        db.execute("INSERT OR REPLACE INTO meta VALUES ('campaign', ?)", (campaign.name,))
        db.execute("INSERT OR REPLACE INTO meta VALUES ('max_gap', ?)",
                   (json.dumps(campaign.max_gap),))
    version = software_version()
    other = db.execute("SELECT software_version, count(*) FROM cases WHERE software_version "
                       "!= ? GROUP BY software_version", (version,)).fetchall()
    if other:
        db.close()
        raise ConfigError(
            f"{db_path} holds {sum(n for _, n in other)} case(s) run by other software ("
            f"{', '.join(v or '?' for v, _ in other)}; this is {version}): a resumed campaign "
            "would mix them; run it into a new --out")
    have = done_ids(db)
    todo = [c for c in campaign.cases if case_id(c) not in have]
    counts = {"run": 0, "skipped": len(campaign.cases) - len(todo), "failed": 0}
    if not todo:
        return counts
    cluster = None
    if scheduler == "local":
        n = workers or os.cpu_count() or 1
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler, timeout=30)
    try:
        futures = [client.submit(run_case, c, campaign.acceptance,
                                 key=f"case-{case_id(c)}", pure=False, retries=2)
                   for c in todo]
        for i, fut in enumerate(as_completed(futures), 1):
            res = fut.result()
            store(db, campaign.name, res, str(db_path))
            counts["run"] += 1
            counts["failed"] += res["verdict"] != "pass"
            if progress is not None:
                progress(i, len(todo), res)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
        db.close()
    return counts


class SeparateCluster:
    """``dask scheduler`` and N ``dask worker`` processes on 127.0.0.1, each its own process
    as on a real cluster (the bench and the tests use it)::

        with SeparateCluster(2, log_dir) as c:
            run(campaign, db, c.url)

    ``c.workers`` are the worker processes (ours, by PID). On leaving, the workers are
    stopped before the scheduler (a worker whose scheduler is gone retries to reach it), each
    SIGTERM then, if it has not ended in ``grace_s``, SIGKILL: nothing is left running."""

    def __init__(self, n_workers: int, log_dir: Optional[Path] = None, grace_s: float = 10.0):
        self.n_workers, self.log_dir, self.grace_s = n_workers, log_dir, grace_s
        self.scheduler = None
        self.workers: list = []
        with socket.socket() as sk:
            sk.bind(("127.0.0.1", 0))
            self.port = sk.getsockname()[1]
        self.url = f"tcp://127.0.0.1:{self.port}"

    def _start(self, argv: list[str], name: str):
        dask = str(Path(sys.executable).parent / "dask")
        out = (open(self.log_dir / f"{name}.log", "w") if self.log_dir is not None
               else subprocess.DEVNULL)
        try:
            return subprocess.Popen([dask, *argv], stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True)
        finally:
            if out is not subprocess.DEVNULL:
                out.close()

    def __enter__(self) -> "SeparateCluster":
        self.scheduler = self._start(["scheduler", "--host", "127.0.0.1", "--port",
                                      str(self.port), "--no-dashboard"], "scheduler")
        try:
            for i in range(self.n_workers):
                self.workers.append(self._start(
                    ["worker", self.url, "--host", "127.0.0.1", "--nthreads", "1",
                     "--no-nanny", "--no-dashboard"], f"worker{i}"))
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        for group in (self.workers, [self.scheduler] if self.scheduler else []):
            for p in group:
                if p.poll() is None:
                    p.terminate()
            for p in group:
                try:
                    p.wait(self.grace_s)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(10)


# ------------------------------------------------------------------ the report
def report(db_path: Path) -> dict:
    """The summary of a campaign database: cases and pass rate; per criterion (each check
    and acceptance clause) its failures; the worst cases by their gap to the vehicle's own
    limit, with the command that reproduces each; per vehicle, mode and grade the mean ratio
    over the seeds with its 95 % confidence interval next to the limit, ``ok`` when the mean
    is at most the campaign's ``max_gap`` above it; the segments driven in more than one
    mode (``MIXED``), with their share under the road-holding override. The verdict: every
    case passes and every mean is ok."""
    if not Path(db_path).is_file():
        raise ConfigError(f"{db_path}: no such campaign database")
    db = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)
    try:
        cases = db.execute("SELECT case_id, vehicle, factors, mode, verdict, failed, command, "
                           "trace_sha256, wall_s FROM cases ORDER BY case_id").fetchall()
        versions = dict(db.execute("SELECT software_version, count(*) FROM cases GROUP BY "
                                   "software_version ORDER BY software_version"))
        segs = db.execute("SELECT s.case_id, c.vehicle, c.factors, s.mode, s.grade, "
                          "s.speed_mps, s.limit_name, s.limit_value, s.gap, s.ok, c.command "
                          "FROM segments s JOIN cases c USING (case_id) WHERE s.gap IS NOT "
                          "NULL").fetchall()
        mixed = db.execute("SELECT c.vehicle, c.factors, s.grade, s.speed_mps, "
                           "json_extract(s.metrics, '$.road_holding_share') FROM segments s "
                           "JOIN cases c USING (case_id) WHERE s.mode = ?", (MIXED,)).fetchall()
        meta = dict(db.execute("SELECT key, value FROM meta"))
    finally:
        db.close()
    name = meta.get("campaign", "?")
    max_gap = json.loads(meta.get("max_gap", "null"))
    criteria: dict[str, int] = {}
    for c in cases:
        for f in json.loads(c[5]):
            key = f.split(":")[1].split()[0] if f.startswith("segment") else f
            criteria[key] = criteria.get(key, 0) + 1
    groups: dict[tuple, list] = {}
    for s in segs:
        vehicle = _label({"name": s[1], "factors": json.loads(s[2])})
        groups.setdefault((vehicle, s[3], s[4], s[6]), []).append((s[7] + s[8], s[7]))
    rows = []
    for (vehicle, mode, grade, limit_name), vals in sorted(groups.items()):
        v = [x for x, _ in vals]
        mean = sum(v) / len(v)
        sd = math.sqrt(sum((x - mean) ** 2 for x in v) / (len(v) - 1)) if len(v) > 1 else 0.0
        half = _t95(len(v) - 1) * sd / math.sqrt(len(v)) if len(v) > 1 else float("nan")
        limit = sum(lim for _, lim in vals) / len(vals)
        rows.append({"vehicle": vehicle, "mode": mode, "grade": grade, "ratio": limit_name,
                     "n": len(v), "mean": mean, "ci95": [mean - half, mean + half],
                     "limit": limit, "gap": mean - limit,
                     "ok": max_gap is None or mean - limit <= max_gap})
    over = sum(not r["ok"] for r in rows)
    if over:
        criteria[f"max_gap (mean ratio over its limit + {max_gap:g}; groups)"] = over
    if len(versions) > 1:
        criteria["one software version (cases of different code)"] = len(cases)
    held: dict[tuple, list] = {}
    for m in mixed:
        held.setdefault((_label({"name": m[0], "factors": json.loads(m[1])}),
                         f"{m[2]}@{m[3]:g}"), []).append(m[4] or 0.0)
    worst = sorted(segs, key=lambda s: -s[8])[:10]
    passed = sum(c[4] == "pass" for c in cases)
    return {"campaign": name, "cases": len(cases), "passed": passed, "max_gap": max_gap,
            "pass_rate": passed / len(cases) if cases else float("nan"),
            "wall_s": sum(c[8] for c in cases),
            "software_versions": versions,
            "failures_by_criterion": dict(sorted(criteria.items(), key=lambda kv: -kv[1])),
            "ratios": rows,
            "mixed": [{"vehicle": v, "segment": seg, "n": len(shares),
                       "road_holding_share": sum(shares) / len(shares)}
                      for (v, seg), shares in sorted(held.items())],
            "worst": [{"case_id": s[0], "vehicle": s[1], "factors": json.loads(s[2]),
                       "mode": s[3], "segment": f"{s[4]}@{s[5]:g}", "ratio": s[6],
                       "value": s[7] + s[8], "limit": s[7], "gap": s[8], "ok": bool(s[9]),
                       "command": s[10]} for s in worst],
            "verdict": "pass" if cases and passed == len(cases) and not over
            and len(versions) == 1 else "fail"}


def _t95(dof: int) -> float:
    """Student's t, two-sided 95 %."""
    from scipy.stats import t

    return float(t.ppf(0.975, dof))


def report_figure(rep: dict, path: Path) -> Path:
    """Each group's mean ratio with its 95 % interval, against its limit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = rep["ratios"]
    fig, ax = plt.subplots(figsize=(9, 0.35 * len(rows) + 1.6))
    y = list(range(len(rows)))
    for i, r in enumerate(rows):
        lo, hi = r["ci95"]
        err = None if math.isnan(lo) else [[r["mean"] - lo], [hi - r["mean"]]]
        ax.errorbar(r["mean"], i, xerr=err, fmt="o", color="C0", capsize=3,
                    label="mean ratio, 95 % CI" if i == 0 else None)
        ax.plot([r["limit"]] * 2, [i - 0.35, i + 0.35], color="C3", lw=2,
                label="the vehicle's limit" if i == 0 else None)
    ax.set_yticks(y, [f"{r['vehicle']} | {r['mode']} {r['grade']} ({r['ratio']})"
                      for r in rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("ratio to the passive twin (lower is better; the limit is the best any "
                  "controller can do)")
    ax.grid(alpha=0.3, axis="x")
    if rows:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax.set_title(f"campaign {rep['campaign']}: {rep['passed']}/{rep['cases']} cases pass",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)
    return path


def render(rep: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    con.print(f"campaign {rep['campaign']}: {rep['passed']}/{rep['cases']} cases pass "
              f"({100 * rep['pass_rate']:.1f} %), {rep['wall_s']:.0f} s of worker time")
    con.print("software: " + "; ".join(f"{v or '?'} ({n} cases)"
                                       for v, n in rep["software_versions"].items()))
    if rep["failures_by_criterion"]:
        t = Table(title="failures by criterion")
        t.add_column("criterion")
        t.add_column("cases", justify="right")
        for k, v in rep["failures_by_criterion"].items():
            t.add_row(k, str(v))
        con.print(t)
    t = Table(title="ratios per vehicle, mode and grade (mean, 95 % CI) against the limit")
    for col in ("vehicle", "mode", "grade", "ratio", "n", "mean", "95 % CI", "limit", "gap",
                "ok"):
        t.add_column(col, justify="right" if col not in ("vehicle", "mode", "ratio") else
                     "left")
    for r in rep["ratios"]:
        lo, hi = r["ci95"]
        t.add_row(r["vehicle"], r["mode"], r["grade"], r["ratio"], str(r["n"]),
                  f"{r['mean']:.3f}", "-" if math.isnan(lo) else f"{lo:.3f}–{hi:.3f}",
                  f"{r['limit']:.3f}", f"{r['gap']:+.3f}", "yes" if r["ok"] else "NO")
    con.print(t)
    if rep["mixed"]:
        t = Table(title="segments driven in more than one mode (judged by no mode's "
                        "acceptance or limit)")
        for col in ("vehicle", "segment", "segments", "under the road-holding override"):
            t.add_column(col)
        for m in rep["mixed"]:
            t.add_row(m["vehicle"], m["segment"], str(m["n"]),
                      f"{100 * m['road_holding_share']:.0f} % of their time")
        con.print(t)
    t = Table(title="worst cases (largest gap to the limit)")
    for col in ("vehicle", "mode", "segment", "value", "limit", "gap", "reproduce"):
        t.add_column(col)
    for w in rep["worst"]:
        t.add_row(_label({"name": w["vehicle"], "factors": w["factors"]}),
                  w["mode"], w["segment"], f"{w['value']:.3f}", f"{w['limit']:.3f}",
                  f"{w['gap']:+.3f}", w["command"])
    con.print(t)
    con.print(f"verdict: {rep['verdict'].upper()}")


# ------------------------------------------------------------------ command line
def main(args) -> int:
    from hil.cli import fail

    try:
        camp = load(args.file)
    except ConfigError as exc:
        fail(str(exc))
    out = Path(args.out or f"out/campaign/{camp.name}")
    db_path = out / "campaign.sqlite"
    sched = args.scheduler
    if sched != "local" and not sched.startswith("tcp://127.0.0.1:"):
        fail(f"--scheduler {sched}: local, or tcp://127.0.0.1:PORT (a scheduler on this host)")
    print(f"campaign {camp.name}: {len(camp.cases)} cases, database {db_path}",
          file=sys.stderr, flush=True)
    bar = _progress(not args.json)
    signal.signal(signal.SIGTERM, _interrupt)   # (as Ctrl-C: a background job ignores SIGINT)
    try:
        with bar as progress:
            counts = run(camp, db_path, sched, args.workers, progress)
    except KeyboardInterrupt:
        print(f"interrupted: the finished cases are in {db_path}; run the same command again "
              "to go on", file=sys.stderr, flush=True)
        return 130
    except OSError as exc:
        fail(f"--scheduler {sched}: {exc}", 3)
    except ConfigError as exc:
        fail(str(exc))
    rep = report(db_path)
    rep["this_run"] = counts
    report_figure(rep, out / "ratios.png")
    (out / "report.json").write_text(json.dumps(_finite(rep), indent=2) + "\n")
    if args.json:
        print(json.dumps(_finite(rep), indent=2))
    else:
        render(rep)
        print(f"report: {out / 'report.json'}, {out / 'ratios.png'}")
    return 0 if rep["verdict"] == "pass" else 1


def _interrupt(*_) -> None:
    raise KeyboardInterrupt


def report_main(args) -> int:
    from hil.cli import fail

    try:
        rep = report(Path(args.db))
    except ConfigError as exc:
        fail(str(exc))
    out = Path(args.out) if args.out else Path(args.db).parent
    out.mkdir(parents=True, exist_ok=True)
    report_figure(rep, out / "ratios.png")
    if args.json:
        print(json.dumps(_finite(rep), indent=2))
    else:
        render(rep)
    return 0 if rep["verdict"] == "pass" else 1


def _progress(enabled: bool):
    """A rich progress bar with ETA on a terminal; lines every 5 % without one."""
    import contextlib

    from hil.cli import progress_lines

    @contextlib.contextmanager
    def bar():
        if not enabled:
            yield None
            return
        if not sys.stderr.isatty():
            lines = progress_lines("campaign")
            yield lambda i, n, res: lines(i, n)
            return
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                   TimeRemainingColumn)

        with Progress(TextColumn("campaign"), BarColumn(), MofNCompleteColumn(),
                      TimeRemainingColumn(), TextColumn("{task.fields[last]}")) as p:
            task = p.add_task("campaign", total=None, last="")
            yield lambda i, n, res: p.update(task, completed=i, total=n,
                                             last=f"{res['case_id']} {res['verdict']}")
    return bar()


def case_main(args) -> int:
    """``hil campaign-case DB CASE_ID``: one case of a campaign database run again, as the
    campaign ran it (the reproduction of a case the hil sim command line cannot express:
    vehicle variants, noise factors)."""
    from hil.cli import fail

    if not Path(args.db).is_file():
        fail(f"campaign-case: {args.db}: no such campaign database")
    con = sqlite3.connect(f"file:{args.db}?mode=ro", uri=True)
    try:
        row = con.execute("SELECT case_json FROM cases WHERE case_id = ?",
                          (args.case_id,)).fetchone()
    finally:
        con.close()
    if row is None:
        fail(f"campaign-case: {args.db} has no case {args.case_id}")
    res = run_case(json.loads(row[0]))
    print(json.dumps(_finite({k: v for k, v in res.items() if k != "case"}), indent=2))
    return 0 if res["verdict"] == "pass" else 1
