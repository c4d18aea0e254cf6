"""The campaign's database (SQLite): its schema, and each case stored as it ends."""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

from calib.errors import ConfigError
from hil.validate.campaign.case import command


SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS cases (
    case_id TEXT PRIMARY KEY,      -- SHA-256 of the case's canonical JSON (first 16 hex)
    campaign TEXT NOT NULL,
    route TEXT NOT NULL, seed INTEGER NOT NULL, vehicle TEXT NOT NULL, factors TEXT NOT NULL,
    mode TEXT NOT NULL, fixed_point INTEGER NOT NULL, noise REAL NOT NULL, duration_s REAL,
    software_version TEXT NOT NULL, calibration_sha256 TEXT NOT NULL,
    design_sha256 TEXT NOT NULL,   -- SHA-256 of the calibration image the case drove with
    trace_sha256 TEXT NOT NULL, verdict TEXT NOT NULL, failed TEXT NOT NULL,
    wall_s REAL NOT NULL, worker TEXT NOT NULL, command TEXT NOT NULL, case_json TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS segments (
    case_id TEXT NOT NULL REFERENCES cases(case_id), idx INTEGER NOT NULL,
    grade TEXT NOT NULL, speed_mps REAL NOT NULL, mode TEXT NOT NULL, scored INTEGER NOT NULL,
    ba_ratio REAL, sws_ratio REAL, dtd_ratio REAL,
    limit_name TEXT,
    limit_value REAL, gap REAL,    -- the limit under the per-drive bound, the value's gap to it
    limit_free REAL, gap_free REAL,    -- the unbounded limit (physical_limits), the gap to it
    sigma REAL,                    -- one drive's scatter of the value (calib.linear.drive_scatter)
    ok INTEGER NOT NULL,
    metrics TEXT NOT NULL,         -- the segment's whole hil sim JSON
    PRIMARY KEY (case_id, idx)
);
CREATE TABLE IF NOT EXISTS infeasible (   -- sampled cars not run ([space]), with the reason
    vehicle TEXT PRIMARY KEY, campaign TEXT NOT NULL, reason TEXT NOT NULL, spec TEXT NOT NULL
);
"""


def open_db(path: Path) -> sqlite3.Connection:
    path.parent.mkdir(parents=True, exist_ok=True)
    db = sqlite3.connect(str(path))
    db.executescript(SCHEMA)
    try:
        check_layout(db, path)
    except ConfigError:
        db.close()
        raise
    return db


def check_layout(db: sqlite3.Connection, path) -> None:
    """ConfigError (one line) for a database of an older layout: its segments have no
    bounded limits, so neither a resumed campaign nor its report could judge them."""
    columns = {r[1] for r in db.execute("PRAGMA table_info(segments)")}
    if "sigma" not in columns:
        raise ConfigError(f"{path}: a campaign database of an older layout (no bounded "
                          "limits): run its campaign again into a new --out")
    columns = {r[1] for r in db.execute("PRAGMA table_info(cases)")}
    if "design_sha256" not in columns:
        raise ConfigError(f"{path}: a campaign database of an older layout (no design "
                          "hashes): run its campaign again into a new --out")


def done_ids(db: sqlite3.Connection) -> set[str]:
    return {r[0] for r in db.execute("SELECT case_id FROM cases")}


def store(db: sqlite3.Connection, campaign: str, res: dict, db_path: str = "DB") -> None:
    """One finished case, in one transaction (a case is in the database whole or not)."""
    c = res["case"]
    with db:
        db.execute("INSERT OR IGNORE INTO cases VALUES "
                   "(?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                   (res["case_id"], campaign, c["route"]["name"], c["seed"],
                    c["vehicle"]["name"], json.dumps(c["vehicle"]["factors"], sort_keys=True),
                    c["mode"], int(c["fixed_point"]), c["noise"], c["duration_s"],
                    res["software_version"], res["calibration_sha256"],
                    res.get("design_sha256", ""), res["trace_sha256"],
                    res["verdict"], json.dumps(res["failed"]), res["wall_s"], res["worker"],
                    command(c, db_path), json.dumps(c, sort_keys=True)))
        for s in res["segments"]:
            r = s["ratio"]
            db.execute("INSERT OR IGNORE INTO segments VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                       (res["case_id"], s["idx"], s["grade"], s["speed_mps"], s["mode"],
                        int(s["scored"]), r.get("ba"), r.get("sws"), r.get("dtd"),
                        s["limit_name"], s["limit_value"], s["gap"], s["limit_free"],
                        s["gap_free"], s["sigma"], int(s["ok"]),
                        json.dumps(finite(s["metrics"]), sort_keys=True)))


def finite(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [finite(v) for v in x]
    return x
