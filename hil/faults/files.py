"""Faults of a file the ECU reads at start: a vehicle file or a gains file with a NaN or an
infinity. The ECU node must refuse it with a one-line error (exit code 2) before it touches
the bus, never with a traceback."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from hil.faults.base import Fault, Result


@dataclass(frozen=True, kw_only=True)
class BrokenFile(Fault):
    """``flag FILE`` for ``python -m hil ecu``, FILE holding ``body`` (``{vehicle}``: the
    default vehicle file with ``key = value``)."""
    node: str = "config"
    ticks: int = 0
    flag: str = "--vehicle"
    filename: str = "broken.toml"
    key: str = ""
    value: str = ""
    body: str = "{vehicle}"

    def text(self) -> str:
        if self.body != "{vehicle}":
            return self.body
        from hil.config import DEFAULT_VEHICLE_FILE

        lines = DEFAULT_VEHICLE_FILE.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.split("=")[0].strip() == self.key:
                lines[i] = f"{self.key} = {self.value}"
                return "\n".join(lines) + "\n"
        raise KeyError(self.key)

    def run(self, out: Path) -> Result:
        path = out / self.filename
        path.write_text(self.text())
        proc = subprocess.run([sys.executable, "-m", "hil", "ecu", self.flag, str(path),
                               "--out", str(out / "config_run")],
                              capture_output=True, text=True, timeout=120,
                              stdin=subprocess.DEVNULL)
        err = proc.stderr.strip()
        crashed = "Traceback" in proc.stderr or proc.returncode not in (0, 2)
        detected = proc.returncode == 2 and self.key in err and len(err.splitlines()) == 1
        return Result(self.name, detected, 0 if detected else None, None, crashed, True,
                      note=err.splitlines()[-1] if err else f"exit {proc.returncode}")

    def table_note(self, r: Result) -> str:
        return "refused: exit 2, one-line error" if r.detected else r.note
