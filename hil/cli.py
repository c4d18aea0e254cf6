"""Shared command-line plumbing: vehicle/route arguments, clear errors, JSON or rich output."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn, Optional

from calib.options import load_options
from calib.vehicle import VehicleConfig
from hil.config import ConfigError, load_vehicle
from hil.sim.road import GRADES, Route, load_route

EXIT_CONFIG = 2


def fail(message: str, code: int = EXIT_CONFIG) -> NoReturn:
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(code)


def add_vehicle_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vehicle", metavar="FILE", default=None,
                        help="vehicle TOML file (default: the paper's Table 3 car)")


def add_calibration_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="the vehicle file the ECU is calibrated for (default: the driven "
                             "car's own): the plant drives --vehicle at that car's ride height, "
                             "the ECU carries that car's calibration")


def add_design_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--design", metavar="FILE", default=None,
                        help="design options TOML ([design] table, calib.options; [calibration] "
                             "table, calib.calpage; default: the documented defaults)")
    add_cache_argument(parser)


def add_cache_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-cache", action="store_true",
                        help="compute the calibration anew, neither reading nor writing the "
                             "design cache (calib/cache.py; SUSPENSION_NO_CACHE=1 does the "
                             "same, and reaches the processes this one starts)")


def apply_cache_argument(args: argparse.Namespace) -> None:
    """``--no-cache``: off for this process and every process it starts (the environment)."""
    if getattr(args, "no_cache", False):
        import os

        from calib import cache

        os.environ[cache.ENV_OFF] = "1"


def add_log_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--start-time", metavar="TIME",
                   help="the run's start: the bus log's first time stamp and the date of its "
                        "ASC, BLF, TRC and MF4 copies (ISO 8601, e.g. 2026-12-02T09:00:00Z, "
                        "or Unix seconds; default: now)")
    p.add_argument("--log-format", action="append", metavar="FMT[,FMT]",
                   help="also write the bus log as bus.asc, bus.blf, bus.trc or bus.mf4 (one "
                        "of asc, blf, trc, mf4, log; repeat or separate by commas); bus.log "
                        "(candump -L) is always written")


def log_options_or_exit(args) -> tuple[int, tuple[str, ...]]:
    """(start time in Unix microseconds, formats) of ``--start-time`` and ``--log-format``;
    bad values exit 2 with one line."""
    from hil.transport.buslog import parse_formats, parse_start_time

    try:
        return (parse_start_time(getattr(args, "start_time", None)),
                parse_formats(getattr(args, "log_format", None)))
    except ValueError as exc:
        fail(str(exc))


def design_or_exit(path: str | None):
    """The design options of ``--design FILE`` (None without it); a bad file exits 2."""
    if path is None:
        return None
    try:
        return load_options(path)
    except ConfigError as exc:
        fail(str(exc))


def add_json_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object on stdout instead of a table")


def grade_arg(text: str) -> str:
    g = text.strip().upper()
    if len(g) != 1 or g not in GRADES:
        raise argparse.ArgumentTypeError(f"grade must be one of {', '.join(GRADES)}, got {text!r}")
    return g


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive and finite, got {text!r}")
    return value


def speed_arg(text: str) -> float:
    value = positive_float(text)
    if value > 100.0:
        raise argparse.ArgumentTypeError(f"speed must be at most 100 m/s, got {text!r}")
    return value


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


def seed_arg(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"seed must be an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"seed must be non-negative, got {text!r}")
    return value


class OneLineParser(argparse.ArgumentParser):
    """argparse with a usage error in one line (exit 2): a missing or bad argument names
    itself and points to ``--help`` instead of printing the whole usage. Sub-commands'
    parsers are of the same class (argparse's ``add_subparsers`` default)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {self.prog}: {message} (--help: the usage)\n")


def run_main(main: Callable[[], int]) -> NoReturn:
    """``sys.exit(main())``, with a ConfigError that escapes (e.g. a broken DBC, loaded at
    import) as one line and exit 2, never a traceback."""
    try:
        code = main()
    except ConfigError as exc:
        fail(str(exc))
    raise SystemExit(code)


_OUT_LOCKS: dict = {}


def lock_out(path: str | Path) -> Path:
    """Create ``--out DIR`` if needed and lock it for this process (``DIR/.lock``, flock): a
    second run on the same directory refuses with one line (exit 2) instead of mixing its
    files into this one's. The lock goes with the process; a process may lock its own
    directory again."""
    import fcntl
    import os

    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fail(f"--out {out}: cannot create the directory: {exc.strerror or exc}")
    if not out.is_dir():
        fail(f"--out {out}: not a directory")
    key = out.resolve()
    if key in _OUT_LOCKS:
        return out
    try:
        fd = os.open(out / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        fail(f"--out {out}: not writable: {exc.strerror or exc}")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        fail(f"--out {out} is in use by another run (pid {holder}); wait for it or choose "
             f"another directory")
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _OUT_LOCKS[key] = fd
    return out


def key_or_exit(path: str | None, required: bool = False) -> Optional[bytes]:
    """The SecOC key of ``--key-file FILE`` (None without it, unless ``required``); a bad
    file exits 2 with one line."""
    from hil.transport.secoc import load_key

    if path is None:
        if required:
            fail("--key-file FILE is required (the SecOC key; `python -m hil keygen FILE` "
                 "makes one, `python -m hil run` one per run)")
        return None
    try:
        return load_key(path)
    except ConfigError as exc:
        fail(str(exc))


def vehicle_or_exit(path: str | None) -> VehicleConfig:
    try:
        return load_vehicle(path)
    except ConfigError as exc:
        fail(str(exc))


def cars_or_exit(vehicle: str | None, calibration: str | None
                 ) -> tuple[VehicleConfig, VehicleConfig]:
    """(the car the plant drives, the car the ECU is calibrated for): ``--vehicle`` at the
    ride height of ``--calibration``'s car (``calib.vehicle.on_calibration``, the campaign's
    ``nominal`` path), and that car; both the driven car without ``--calibration``."""
    from calib.vehicle import on_calibration

    car = vehicle_or_exit(vehicle)
    if calibration is None:
        return car, car
    cal = vehicle_or_exit(calibration)
    if cal.sim.plant_dt_s != car.sim.plant_dt_s:
        fail(f"--calibration {calibration}: its tick ({cal.sim.plant_dt_s:g} s) is not the "
             f"driven car's plant step ({car.sim.plant_dt_s:g} s)")
    return on_calibration(car, cal), cal


def route_or_exit(spec: str) -> Route:
    try:
        return load_route(spec)
    except ConfigError as exc:
        fail(str(exc))


def _clean(value: Any) -> Any:
    """JSON has no NaN/inf: write them as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def emit(obj: dict, as_json: bool, render: Callable[[dict], None]) -> None:
    if as_json:
        json.dump(_clean(obj), sys.stdout, indent=2, sort_keys=False)
        sys.stdout.write("\n")
    else:
        render(obj)


PROGRESS_STEP_PCT = 5


def progress_lines(label: str, detail: Optional[Callable[[], str]] = None
                   ) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that prints ``label: NN %`` (and ``detail()``)
    on stderr each time another ``PROGRESS_STEP_PCT`` percent is done, and at 100 %."""
    import time

    last = [-1]
    t0 = time.monotonic()

    def progress(done: int, total: int) -> None:
        pct = 100 * done // max(1, total)
        step = pct - pct % PROGRESS_STEP_PCT
        if step > last[0]:
            last[0] = step
            extra = f"  {detail()}" if detail is not None else ""
            print(f"{label}: {step:3d} %  ({time.monotonic() - t0:.0f} s){extra}",
                  file=sys.stderr, flush=True)
    return progress


@contextlib.contextmanager
def progress_bar(label: str, enabled: bool) -> Iterator[Optional[Callable[[int, int], None]]]:
    """A transient rich progress bar on stderr for long work, as a ``progress(done, total)``
    callback; without a terminal, a line every ``PROGRESS_STEP_PCT`` percent instead (a CI
    log, ``make run | tee``); ``None`` when disabled (JSON output)."""
    if not enabled:
        yield None
        return
    if not sys.stderr.isatty():
        yield progress_lines(label)
        return
    from rich.progress import Progress

    bar = Progress(transient=True)
    bar.start()
    task = bar.add_task(label, total=1)
    try:
        yield lambda done, total: bar.update(task, completed=done, total=total)
    finally:
        bar.stop()


def write_atomic(path: Path | str, text: str | bytes) -> Path:
    """``text`` into ``path`` whole or not at all: written to ``path.tmp``, then renamed over
    ``path``; on any failure (a full disk) the temporary file is removed and the error
    raised, so no ``*.tmp`` stays behind."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        if isinstance(text, bytes):
            tmp.write_bytes(text)
        else:
            tmp.write_text(text)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
