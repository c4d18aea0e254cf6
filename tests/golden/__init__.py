"""Golden traces (openpilot process-replay style): a fixed set of SIL scenarios whose trace
hash, bus-log hash and report metrics are pinned in ``tests/golden/golden.json``.

    python -m tests.golden            # check every scenario against golden.json (exit 1 on a diff)
    python -m tests.golden --update   # rewrite golden.json (say why in the same commit)

What each pinned value covers and what is ignored: ``tests/golden/README.md``.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
GOLDEN_FILE = HERE / "golden.json"
ROUTES = HERE / "routes"
# the SecOC key of the golden runs (a test key, public: the bus.log bytes depend on it; a
# copy with mode 0600 serves as --key-file, see README.md)
KEY_FILE = HERE / "secoc.key"


def secoc_key() -> bytes:
    return bytes.fromhex(KEY_FILE.read_text().strip())


def key_file(directory: Path) -> Path:
    """A copy of the golden key as a key file ``hil`` accepts (mode 0600) in ``directory``."""
    import os

    path = Path(directory) / "golden_secoc.key"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(KEY_FILE.read_text())
    return path
# the golden runs' start time: their bus logs' first time stamp (hil sim --start-time)
START_TIME = "2026-01-01T00:00:00Z"
# report keys that are not behaviour: the vehicle file's path as given
IGNORED_REPORT_KEYS = ("vehicle",)


@dataclass(frozen=True)
class Scenario:
    name: str
    route: str                      # shipped route name or a file under tests/golden/routes
    mode: str
    seed: int = 1
    vehicle: Optional[str] = None   # path relative to the project root (None: Table 3 car)
    fixed_point: bool = False
    duration_s: Optional[float] = None
    per_tick: bool = False          # the ECU trace is stored tick by tick too (ticks.py)

    def command(self) -> str:
        """The ``hil sim`` command line that gives the same trace and bus log."""
        parts = ["python -m hil sim", f"--route {self.route}", f"--mode {self.mode}",
                 f"--seed {self.seed}"]
        if self.vehicle:
            parts.append(f"--vehicle {self.vehicle}")
        if self.fixed_point:
            parts.append("--fixed-point")
        if self.duration_s is not None:
            parts.append(f"--duration {self.duration_s:g}")
        return " ".join(parts + ["--key-file KEY", f"--start-time {START_TIME}", "--out DIR"])


SCENARIOS = (
    Scenario("full_road_section_auto", "full_road_section", "auto"),
    Scenario("comfort_b", "tests/golden/routes/b20.toml", "comfort", per_tick=True),
    Scenario("safety_c", "tests/golden/routes/c15.toml", "safety"),
    Scenario("comprehensive_d", "tests/golden/routes/d10.toml", "comprehensive"),
    Scenario("regen_a", "tests/golden/routes/a25.toml", "regen"),
    Scenario("fixed_point_auto", "full_road_section", "auto", fixed_point=True,
             duration_s=60.0, per_tick=True),
    Scenario("suv_auto", "full_road_section", "auto", vehicle="hil/vehicles/suv.toml"),
)
BY_NAME = {s.name: s for s in SCENARIOS}


def run(s: Scenario, trace: Optional[list] = None, ticks: Optional[list] = None) -> dict:
    """Run one scenario in process as ``hil sim --out`` does; the pinned values. ``trace`` (a
    list) receives the run's per-tick trace (``hil.nodes.sil.SilTrace``), ``ticks`` (a list) the
    ECU's per-tick inputs and outputs as columns (``tests.golden.ticks``)."""
    from hil.nodes import sil
    from hil.transport.buslog import SIL_CHANNEL, BusLogFile, parse_start_time
    from hil.cli import _clean
    from hil.config import load_vehicle
    from hil.nodes import LockstepClock
    from hil.sim.road import load_route

    cfg = load_vehicle(ROOT / s.vehicle if s.vehicle else None)
    route = load_route(str(ROOT / s.route) if "/" in s.route else s.route)
    with tempfile.TemporaryDirectory() as tmp:
        log = BusLogFile(Path(tmp) / "bus.log", SIL_CHANNEL, parse_start_time(START_TIME))
        clock = LockstepClock(cfg.sim.plant_dt_s)
        hashed = bytearray() if ticks is not None else None
        try:
            report, tr = sil.run(cfg, route, s.mode, s.seed, fixed_point=s.fixed_point,
                                 duration_s=s.duration_s, key=secoc_key(), hashed=hashed,
                                 on_frame=lambda fid, data: log.write(fid, data, clock.stamp(fid)))
        finally:
            log.close()
        buslog_sha = hashlib.sha256(log.path.read_bytes()).hexdigest()
    # (the scenario's command is hil sim's: its ride verdict too, hil.validate.ride)
    from hil.validate import ride

    ride.attach(report, cfg, route, sil.ecu_params(cfg, s.mode))
    if trace is not None:
        trace.append(tr)
    if ticks is not None:
        from tests.golden import ticks as per_tick

        ticks.append(per_tick.columns(hashed))
    metrics = json.loads(json.dumps(_clean(report)))
    for key in IGNORED_REPORT_KEYS:
        metrics.pop(key, None)
    return {"command": s.command(), "trace_sha256": report["trace_sha256"],
            "buslog_sha256": buslog_sha, "frames_logged": log.count, "report": metrics}


def load() -> dict:
    return json.loads(GOLDEN_FILE.read_text())


# the fault campaign over the hub, pinned beside the scenarios (``faults.json``): every fault's
# row (detection, reaction and recovery ticks, fault bits, DTCs, notes), its out directory
# written as DIR and the project's as ROOT. make test's campaign and make vcan-test's on vcan0 are each compared with it.
FAULTS = "faults"
FAULTS_FILE = HERE / "faults.json"
FAULTS_COMMAND = "python -m hil faults -i remote --json --out DIR"


def fault_rows(rows: list, out: Path) -> list:
    """``hil faults`` result rows with their out directory's path written as DIR and the
    project's as ROOT (notes name files)."""
    return json.loads(json.dumps(rows).replace(str(out), "DIR").replace(str(ROOT), "ROOT"))


def run_faults() -> dict:
    """The fault campaign over the hub, as FAULTS_COMMAND runs it; the pinned values."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "faults"
        proc = subprocess.run([sys.executable, "-m", "hil", "faults", "-i", "remote", "--json",
                               "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                              timeout=1200)
        if proc.returncode != 0:
            raise RuntimeError(f"{FAULTS_COMMAND} exited {proc.returncode}: "
                               f"{proc.stderr.strip()[-2000:]}")
        return {"command": FAULTS_COMMAND,
                "results": fault_rows(json.loads(proc.stdout)["results"], out)}


def load_faults() -> dict:
    return json.loads(FAULTS_FILE.read_text())


def diff(want, got, path: str = "") -> list[str]:
    """Where two JSON values differ (paths), at most 20."""
    out: list[str] = []
    if isinstance(want, dict) and isinstance(got, dict):
        for k in sorted(set(want) | set(got)):
            if k not in want or k not in got:
                out.append(f"{path}/{k}: {'missing' if k not in got else 'unexpected'}")
            else:
                out += diff(want[k], got[k], f"{path}/{k}")
    elif isinstance(want, list) and isinstance(got, list) and len(want) == len(got):
        for i, (a, b) in enumerate(zip(want, got)):
            out += diff(a, b, f"{path}[{i}]")
    elif want != got or type(want) is not type(got):
        out.append(f"{path}: want {want!r}, got {got!r}")
    return out[:20]
