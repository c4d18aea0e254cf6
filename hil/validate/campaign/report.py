"""A campaign database's summary: pass rate, failures per criterion, the mean ratio per
vehicle, mode and grade against its limit, the worst cases; its figure and text."""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path

from calib.errors import ConfigError
from hil.validate.campaign import space_report
from hil.validate.campaign.case import MIXED, calibration_key
from hil.validate.campaign.spec import label
from hil.validate.campaign.store import check_layout

MAX_ROWS = 40             # groups the text report lists whole (report.json has every one)


def report(db_path: Path) -> dict:
    """The summary of a campaign database: cases and pass rate; per criterion (each check
    and acceptance clause) its failures; the worst cases by their gap to the vehicle's own
    limit, with the command that reproduces each; per vehicle, mode and grade the mean value
    over the seeds with its 95 % confidence interval next to the limit under the per-drive
    bound (the judged gap) and the unbounded limit (the gap beside it), ``ok`` when the mean
    gap is at most the campaign's ``max_gap`` plus 2 sigma / sqrt(n), sigma one drive's
    scatter from the model (``calib.linear.drive_scatter``, known before the run); the
    segments driven in more than one mode (``MIXED``), with their share under the
    road-holding override. The verdict: every case passes and every mean is ok."""
    cases, versions, segs, mixed, meta, infeasible, designs = _read(db_path)
    name = meta.get("campaign", "?")
    max_gap = json.loads(meta.get("max_gap", "null"))
    criteria: dict[str, int] = {}
    for c in cases:
        for f in json.loads(c[5]):
            key = f.split(":")[1].split()[0] if f.startswith("segment") else f
            criteria[key] = criteria.get(key, 0) + 1
    groups: dict[tuple, list] = {}
    for s in segs:
        vehicle = _name(s[1], s[2], s[14])
        groups.setdefault((vehicle, s[3], s[4], s[6]), []).append(s)
    rows = [_group(key, vals, max_gap) for key, vals in sorted(groups.items())]
    over = sum(not r["ok"] for r in rows)
    if over:
        criteria[f"max_gap (mean over its bounded limit + {max_gap:g} + 2 sigma/sqrt n; "
                 "groups)"] = over
    if len(versions) > 1:
        criteria["one software version (cases of different code)"] = len(cases)
    split = split_designs(designs)
    if split:
        criteria["one design per car (cases of one car drove other calibrations)"] = split
    held: dict[tuple, list] = {}
    for m in mixed:
        held.setdefault((_name(m[0], m[1], m[5]),
                         f"{m[2]}@{m[3]:g}"), []).append(m[4] or 0.0)
    worst = sorted(segs, key=lambda s: (-s[8], s[0], s[4]))[:10]
    passed = sum(c[4] == "pass" for c in cases)
    space = space_report.summary(db_path)
    if space is not None:
        space["campaign"] = name
    return {"campaign": name, "cases": len(cases), "passed": passed, "max_gap": max_gap,
            "pass_rate": passed / len(cases) if cases else float("nan"),
            "pass_rate_ci95": list(space_report.proportion_ci(passed, len(cases))),
            "wall_s": sum(c[8] for c in cases),
            "software_versions": versions,
            "designs": len({h for _, h in designs if h}), "split_designs": split,
            "failures_by_criterion": dict(sorted(criteria.items(), key=lambda kv: -kv[1])),
            "ratios": rows,
            "mixed": [{"vehicle": v, "segment": seg, "n": len(shares),
                       "road_holding_share": sum(shares) / len(shares)}
                      for (v, seg), shares in sorted(held.items())],
            "infeasible": [{"vehicle": v, "reason": r} for v, r in infeasible],
            "infeasible_share": len(infeasible) / max(1, len(infeasible) + len(
                {(c[1], c[2]) for c in cases})),
            "worst": [{"case_id": s[0], "vehicle": s[1], "car": _name(s[1], s[2], s[14]),
                       "factors": json.loads(s[2]),
                       "mode": s[3], "segment": f"{s[4]}@{s[5]:g}", "ratio": s[6],
                       "value": s[7] + s[8], "limit": s[7], "gap": s[8], "ok": bool(s[9]),
                       "command": s[10], "limit_free": s[11], "gap_free": s[12]}
                      for s in worst],
            "space": space,
            "verdict": "pass" if cases and passed == len(cases) and not over
            and len(versions) == 1 and not split else "fail"}


def split_designs(designs: list) -> int:
    """The cases whose calibration car (``case.calibration_key``) drove with more than one
    calibration image (``design_sha256``) in the database: 0 when every worker drove each car
    with the same bytes."""
    by_car: dict[str, set] = {}
    count: dict[str, int] = {}
    for case_json, sha in designs:
        if not sha:
            continue
        key = calibration_key(json.loads(case_json))
        by_car.setdefault(key, set()).add(sha)
        count[key] = count.get(key, 0) + 1
    return sum(count[k] for k, hashes in by_car.items() if len(hashes) > 1)


def _read(db_path: Path) -> tuple:
    """The rows a report is made of: cases, software versions, judged segments, mixed
    segments, meta, infeasible cars."""
    if not Path(db_path).is_file():
        raise ConfigError(f"{db_path}: no such campaign database")
    db = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)
    try:
        cases = db.execute("SELECT case_id, vehicle, factors, mode, verdict, failed, command, "
                           "trace_sha256, wall_s FROM cases ORDER BY case_id").fetchall()
        versions = dict(db.execute("SELECT software_version, count(*) FROM cases GROUP BY "
                                   "software_version ORDER BY software_version"))
        check_layout(db, db_path)
        segs = db.execute("SELECT s.case_id, c.vehicle, c.factors, s.mode, s.grade, "
                          "s.speed_mps, s.limit_name, s.limit_value, s.gap, s.ok, c.command, "
                          "s.limit_free, s.gap_free, s.sigma, json_extract(c.case_json, "
                          "'$.vehicle.sample') FROM segments s JOIN cases c USING (case_id) "
                          "WHERE s.gap IS NOT NULL").fetchall()
        mixed = db.execute("SELECT c.vehicle, c.factors, s.grade, s.speed_mps, "
                           "json_extract(s.metrics, '$.road_holding_share'), json_extract("
                           "c.case_json, '$.vehicle.sample') FROM segments s "
                           "JOIN cases c USING (case_id) WHERE s.mode = ?", (MIXED,)).fetchall()
        meta = dict(db.execute("SELECT key, value FROM meta"))
        designs = db.execute("SELECT case_json, design_sha256 FROM cases").fetchall()
        try:
            infeasible = db.execute("SELECT vehicle, reason FROM infeasible ORDER BY vehicle"
                                    ).fetchall()
        except sqlite3.OperationalError:      # (a database from before [space])
            infeasible = []
    finally:
        db.close()
    return cases, versions, segs, mixed, meta, infeasible, designs


def _name(vehicle: str, factors: str, sample) -> str:
    """A group's vehicle: a sampled car by its number (its factors are in the space's
    table), a listed variant by its factors."""
    if sample is not None:
        return f"{vehicle} car {sample}"
    return label({"name": vehicle, "factors": json.loads(factors)})


def _group(key: tuple, segs: list, max_gap) -> dict:
    """One vehicle's mode and grade over its drives: the mean value, its 95 % interval, both
    limits and gaps, one drive's model scatter sigma and the rule (b) tolerance."""
    vehicle, mode, grade, limit_name = key
    n = len(segs)
    v = [s[7] + s[8] for s in segs]
    mean = sum(v) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in v) / (n - 1)) if n > 1 else 0.0
    half = _t95(n - 1) * sd / math.sqrt(n) if n > 1 else float("nan")
    limit = sum(s[7] for s in segs) / n
    free = sum(s[11] for s in segs) / n
    # (sigma none: a drive too short for the bounded limit, judged on the unbounded one)
    sigma = sum(s[13] or 0.0 for s in segs) / n
    tol = None if max_gap is None else max_gap + 2.0 * sigma / math.sqrt(n)
    return {"vehicle": vehicle, "mode": mode, "grade": grade, "ratio": limit_name, "n": n,
            "mean": mean, "ci95": [mean - half, mean + half], "limit": limit,
            "gap": mean - limit, "limit_free": free, "gap_free": mean - free, "sigma": sigma,
            "tolerance": tol, "ok": tol is None or mean - limit <= tol}


def _t95(dof: int) -> float:
    """Student's t, two-sided 95 %."""
    from scipy.stats import t

    return float(t.ppf(0.975, dof))


def shown_groups(rows: list) -> list:
    """The groups the text and the figure show: all up to ``MAX_ROWS``, else those not ok
    and the ten largest gaps."""
    if len(rows) <= MAX_ROWS:
        return rows
    return ([r for r in rows if not r["ok"]]
            + sorted((r for r in rows if r["ok"]), key=lambda r: -r["gap"])[:10])


def report_figure(rep: dict, path: Path) -> Path:
    """Each group's mean ratio with its 95 % interval, against its limits (``shown_groups``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = shown_groups(rep["ratios"])
    fig, ax = plt.subplots(figsize=(9, 0.35 * len(rows) + 1.6))
    y = list(range(len(rows)))
    for i, r in enumerate(rows):
        lo, hi = r["ci95"]
        err = None if math.isnan(lo) else [[r["mean"] - lo], [hi - r["mean"]]]
        ax.errorbar(r["mean"], i, xerr=err, fmt="o", color="C0", capsize=3,
                    label="mean ratio, 95 % CI" if i == 0 else None)
        ax.plot([r["limit"]] * 2, [i - 0.35, i + 0.35], color="C3", lw=2,
                label="the vehicle's limit under the per-drive bound" if i == 0 else None)
        ax.plot([r["limit_free"]] * 2, [i - 0.35, i + 0.35], color="C3", lw=1, ls=":",
                label="its unbounded limit" if i == 0 else None)
    ax.set_yticks(y, [f"{r['vehicle']} | {r['mode']} {r['grade']} ({r['ratio']})"
                      for r in rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("ratio to the passive twin (lower is better; the limit is the best any "
                  "controller can do)")
    ax.grid(alpha=0.3, axis="x")
    if rows:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    more = "" if len(rows) == len(rep["ratios"]) else (
        f" ({len(rows)} of {len(rep['ratios'])} groups: those not ok, the largest gaps)")
    ax.set_title(f"campaign {rep['campaign']}: {rep['passed']}/{rep['cases']} cases pass{more}",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)
    return path


def render(rep: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    lo, hi = rep["pass_rate_ci95"]
    con.print(f"campaign {rep['campaign']}: {rep['passed']}/{rep['cases']} cases pass "
              f"({100 * rep['pass_rate']:.1f} %, 95 % CI {100 * lo:.1f}–{100 * hi:.1f} %), "
              f"{rep['wall_s']:.0f} s of worker time")
    con.print("software: " + "; ".join(f"{v or '?'} ({n} cases)"
                                       for v, n in rep["software_versions"].items()))
    if rep.get("infeasible"):
        con.print(f"{len(rep['infeasible'])} sampled cars not run "
                  f"({100 * rep['infeasible_share']:.1f} % of the space), each for its reason:")
        for x in rep["infeasible"]:
            con.print(f"  {x['vehicle']}: {x['reason']}")
    if rep["failures_by_criterion"]:
        t = Table(title="failures by criterion")
        t.add_column("criterion")
        t.add_column("cases", justify="right")
        for k, v in rep["failures_by_criterion"].items():
            t.add_row(k, str(v))
        con.print(t)
    rows = rep["ratios"]
    shown = shown_groups(rows)
    what = "" if shown is rows else (f" ({len(shown)} of {len(rows)}: those not ok and the "
                                     "10 largest gaps; all in report.json)")
    t = Table(title="the mean over the seeds against the limit under the per-drive bound "
                    "(ok: gap <= tol = max_gap + 2 sigma/sqrt n) and the unbounded limit"
                    + what)
    for col in ("vehicle", "segment", "n", "mean", "limit", "gap", "tol", "unbounded",
                "ok"):
        t.add_column(col, justify="left" if col in ("vehicle", "segment") else "right")
    for r in shown:
        t.add_row(r["vehicle"], f"{r['mode']} {r['grade']}", str(r["n"]),
                  f"{r['mean']:.3f}", f"{r['limit']:.3f}", f"{r['gap']:+.3f}",
                  "-" if r["tolerance"] is None else f"{r['tolerance']:.3f}",
                  f"{r['limit_free']:.3f} ({r['gap_free']:+.3f})",
                  "yes" if r["ok"] else "NO")
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
    con.print("worst cases (largest gap to the limit under the per-drive bound), each with "
              "the command that reproduces it:")
    for w in rep["worst"]:
        con.print(f"  {w['car']}, {w['mode']} "
                  f"{w['segment']}: {w['value']:.3f}, limit {w['limit']:.3f}, gap "
                  f"{w['gap']:+.3f}\n    {w['command']}", soft_wrap=True)
    if rep.get("space"):
        space_report.render(rep["space"], con)
    con.print(f"verdict: {rep['verdict'].upper()}")
