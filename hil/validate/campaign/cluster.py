"""Running a campaign's cases on Dask: a LocalCluster, a running scheduler, or a separate
scheduler with its workers (``SeparateCluster``)."""

from __future__ import annotations

import hashlib
import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Optional

from calib.errors import ConfigError
from hil.validate.campaign.case import calibration_key, design, run_case, software_version
from hil.validate.campaign.spec import Campaign, case_id, label
from hil.validate.campaign.store import done_ids, open_db, store

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
        db.executemany("INSERT OR REPLACE INTO infeasible VALUES (?, ?, ?, ?)",
                       [(label(x["vehicle"]), campaign.name, x["reason"],
                         json.dumps(x["vehicle"], sort_keys=True))
                        for x in campaign.infeasible])
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
        # one design per calibration car, on one worker, carried to each of its cases
        designs = {}
        for c in todo:
            k = calibration_key(c)
            if k not in designs:
                tag = hashlib.sha256(k.encode()).hexdigest()[:16]
                designs[k] = client.submit(design, c, key=f"design-{tag}", pure=False,
                                           retries=2)
        futures = [client.submit(run_case, c, campaign.acceptance, designs[calibration_key(c)],
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
