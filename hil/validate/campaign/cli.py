"""The campaign commands: ``hil campaign``, ``hil campaign-report``, ``hil campaign-case``."""

from __future__ import annotations

import json
import signal
import sqlite3
import sys
from pathlib import Path

from calib.errors import ConfigError
from hil.validate.campaign.case import run_case
from hil.validate.campaign.cluster import run
from hil.validate.campaign.report import render, report, report_figure
from hil.validate.campaign.spec import load
from hil.validate.campaign.store import finite

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
    figures(rep, out)
    (out / "report.json").write_text(json.dumps(finite(rep), indent=2) + "\n")
    if args.json:
        print(json.dumps(finite(rep), indent=2))
    else:
        render(rep)
        print(f"report: {out / 'report.json'}, figures: {out}/*.png")
    return 0 if rep["verdict"] == "pass" else 1


def figures(rep: dict, out: Path) -> list[Path]:
    """The report's figures: ``ratios.png`` (each group's mean against its limits) and, for a
    space, per base car ``space_BASE.png`` and ``passfail_BASE.png``."""
    from hil.validate.campaign import space_report

    paths = [report_figure(rep, out / "ratios.png")]
    if rep.get("space"):
        paths += space_report.figures(rep["space"], out)
    return paths


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
    figures(rep, out)
    if args.cars:
        from hil.cli import write_atomic
        from hil.validate.campaign import space_report

        write_atomic(Path(args.cars), space_report.cars_markdown(rep))
    if args.json:
        print(json.dumps(finite(rep), indent=2))
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
    print(json.dumps(finite({k: v for k, v in res.items() if k != "case"}), indent=2))
    return 0 if res["verdict"] == "pass" else 1
