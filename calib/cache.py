"""The design cache: a calibration computed once is read back by every later process.

``build`` (the ECU's calibration from a vehicle: Riccati solves, the comfort polish, the grade
tables, the fault-detection levels) takes most of a second, and every process that drives a
car needs one: ``hil sim``, each node of ``hil run``, each campaign worker and test process.
Its result is a pure function of its inputs, so it is kept on disk under a key that digests
every one of them:

- the vehicle configuration as parsed (``repr``: every value, whatever file it came from) and
  the design options, and the gains file's bytes (or that there is none: tuned at build time);
- the design code itself: the source of every module of ``calib`` and of the firmware's
  calibration types (``firmware/params.py``, ``firmware/fx/tables.py``);
- the numeric stack: Python, numpy and scipy versions, and OpenBLAS's pinned kernels
  (``calib.blas``), whose summation order reaches the last bits.

An entry is written to a temporary file in the same directory and renamed into place (atomic
on POSIX), so concurrent processes (two test workers, Dask workers, the nodes of one run)
never read half an entry; two that compute the same entry at once write the same bytes. An
entry that cannot be read (a different pickle, a truncated disk) is computed again and
rewritten. Cold and warm give the same bytes (``tests/test_cache.py``).

Where: ``$SUSPENSION_CACHE_DIR``, else ``$XDG_CACHE_HOME/suspension-ecu``, else
``~/.cache/suspension-ecu`` (created with mode 0700: entries are pickles, read only from the
user's own directory), one folder per version of the design code (``DIGEST/KIND/KEY.pickle``:
a change of the code leaves the older folders behind, unread). ``SUSPENSION_NO_CACHE=1`` (``--no-cache`` on every ``hil`` command)
computes everything and neither reads nor writes; ``python -m hil cache --clear`` empties it.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import platform
import sys
import tempfile
from pathlib import Path
from typing import Callable, TypeVar

T = TypeVar("T")
ENV_DIR = "SUSPENSION_CACHE_DIR"
ENV_OFF = "SUSPENSION_NO_CACHE"
ROOT = Path(__file__).resolve().parents[1]
# the code whose result is cached: the design (calib) and the calibration's types
CODE = (ROOT / "calib", ROOT / "firmware" / "params.py", ROOT / "firmware" / "fx" / "tables.py")
FORMAT = 1          # the entry's layout (bump when what is pickled changes shape)


def directory() -> Path:
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "suspension-ecu"


def enabled() -> bool:
    return os.environ.get(ENV_OFF, "") in ("", "0")


_code_digest: str | None = None


def code_digest() -> str:
    """SHA-256 over the design code's source files (path and bytes, in sorted order) and the
    numeric stack's versions and kernels; computed once per process."""
    global _code_digest
    if _code_digest is None:
        import numpy
        import scipy

        h = hashlib.sha256()
        files = sorted(p for c in CODE for p in ([c] if c.is_file() else c.rglob("*.py")))
        for p in files:
            h.update(str(p.relative_to(ROOT)).encode() + b"\0" + p.read_bytes() + b"\0")
        # (OpenBLAS's kernels: the pinned core, or on a host calib.blas leaves alone the
        # CPU itself, which chooses them)
        core = os.environ.get("OPENBLAS_CORETYPE") or f"unpinned {_cpu()}"
        h.update(f"format {FORMAT} python {platform.python_version()} numpy "
                 f"{numpy.__version__} scipy {scipy.__version__} machine "
                 f"{platform.machine()} openblas {core} "
                 f"threads {os.environ.get('OPENBLAS_NUM_THREADS', '')}".encode())
        _code_digest = h.hexdigest()
    return _code_digest


def _cpu() -> str:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            return next((line.split(":", 1)[1].strip() for line in f
                         if line.startswith(("model name", "flags"))), "")
    except OSError:
        return platform.processor()


def key(kind: str, *parts: bytes) -> str:
    h = hashlib.sha256(f"{kind}\0{code_digest()}\0".encode())
    for p in parts:
        h.update(len(p).to_bytes(8, "little") + p)
    return h.hexdigest()


def cached(kind: str, parts: tuple[bytes, ...], compute: Callable[[], T]) -> T:
    """``compute()``'s result, from the cache when an entry for (``kind``, ``parts``, the
    design code) is there, else computed and stored. Exceptions of ``compute`` pass through
    (nothing is stored)."""
    if not enabled():
        return compute()
    path = directory() / code_digest()[:16] / kind / f"{key(kind, *parts)}.pickle"
    try:
        with open(path, "rb") as f:
            return pickle.load(f)
    except FileNotFoundError:
        pass
    except Exception:        # (unreadable: computed and written again below)
        pass
    value = compute()
    _store(path, value)
    return value


def _store(path: Path, value) -> None:
    """Write atomically; a cache that cannot be written is no error (the value stands)."""
    try:
        directory().mkdir(parents=True, exist_ok=True, mode=0o700)
        path.parent.parent.mkdir(exist_ok=True, mode=0o700)
        path.parent.mkdir(exist_ok=True, mode=0o700)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".pickle")
        try:
            with os.fdopen(fd, "wb") as f:
                pickle.dump(value, f, protocol=5)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError as exc:
        print(f"warning: design cache not written ({path.parent}: {exc.strerror or exc})",
              file=sys.stderr)


def clear() -> int:
    """Remove every entry (and numba's compiled code kept beside them, ``calib.jitcache``);
    returns how many entries."""
    import shutil

    n = 0
    base = directory()
    if base.is_dir():
        for p in base.rglob("*.pickle"):
            p.unlink(missing_ok=True)
            n += 1
        shutil.rmtree(base / "numba", ignore_errors=True)
    return n
