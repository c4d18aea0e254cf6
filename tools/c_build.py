"""The C fixed-point path built and fed as its tests and benchmarks do: gcc at fixed flags
(C99, every warning an error, ``-O2``) over ``c/`` and the generated tables, and a recorded
trace as the stdin of ``c/trace_replay.c``."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
C_DIR = ROOT / "c"
GEN = C_DIR / "generated"
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2")
REPLAY_SOURCES = (C_DIR / "ecu_fx.c", C_DIR / "trace_replay.c", GEN / "ecu_tables.c")


class CBuildError(RuntimeError):
    pass


def gcc() -> str:
    cc = shutil.which("gcc")
    if not cc:
        raise CBuildError("gcc is needed for the C path (Debian: apt-get install gcc)")
    return cc


def compile_c(out: Path, sources, *extra, gen: Path = GEN) -> Path:
    """Compile ``sources`` to ``out`` against the tables header in ``gen``; a warning or an
    error raises CBuildError with the command and gcc's output."""
    cmd = [gcc(), *CFLAGS, f"-I{gen}", f"-I{C_DIR}", *extra, *map(str, sources), "-o",
           str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0 or res.stderr:
        raise CBuildError(f"{' '.join(cmd)}\n{res.stderr}")
    return Path(out)


def replay_input(rec) -> str:
    """A fixed-point run's record (``hil.nodes.sil.run(fx_record=...)``: per tick the
    ``firmware.fx.state.TickIn`` and the outputs) as ``trace_replay``'s stdin."""
    def line(i):
        counts = [-1 if v is None else v for v in i.counts]
        return " ".join(map(str, [*counts, *i.k_q, *i.r_q, i.want, int(i.passive),
                                  int(i.fault), int(i.regen), int(i.reset)]))
    return "\n".join(line(i) for i, _ in rec) + "\n"
