"""OpenBLAS set up before numpy loads: the same kernels on every x86-64 host, one thread.

numpy and scipy call OpenBLAS, which picks its kernels for the CPU when the library loads
(``Haswell`` for AVX2, ``SkylakeX`` for AVX-512, ...). The kernels sum in different orders.
The calibration no longer depends on them (``calib.exact``, ``calib.grid``, the committed
data of ``calib.dataset``: docs/calibration.md, ``tests/test_kernels.py``); the pin to
``Haswell`` wherever the CPU has AVX2 and FMA stays, so that what else calls BLAS does so
alike on every such host.

OpenBLAS reads ``OPENBLAS_CORETYPE`` when it loads, so :func:`pin` runs when ``hil`` is
imported: ``tools`` and the test suite (``tests/conftest.py``) import ``hil`` first, and
``firmware`` stays free of host matters (docs/architecture.md). It keeps a value already in the
environment (an explicit choice), does nothing on a CPU without AVX2 and FMA or off x86-64
(those hosts may differ in the last bits), and warns when numpy was imported before it,
since the kernels are chosen by then. Child processes inherit the variable.

It also sets ``OPENBLAS_NUM_THREADS=1`` (unless set): every matrix here is at most 10 x 10,
and on this 2-core machine numpy's and scipy's worker threads spun after the small calls,
burning 22 us of CPU per 75 us SIL tick on the other core (process CPU time 97 us per tick
against 75 us of wall time; with one thread both are 75 us), a core that ``hil run``'s node
processes need. Same bytes either way (full road section); GA tuning time unchanged.
"""

from __future__ import annotations

import ctypes
import glob
import os
import platform
import sys
import warnings

VAR = "OPENBLAS_CORETYPE"
CORE = "Haswell"
THREADS_VAR = "OPENBLAS_NUM_THREADS"


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def wanted_core() -> str | None:
    """The core to pin on this host (None: leave OpenBLAS's own choice)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    return CORE if {"avx2", "fma"} <= _cpu_flags() else None


def pin() -> None:
    want = {}
    if THREADS_VAR not in os.environ:
        want[THREADS_VAR] = "1"
    core = wanted_core()
    if core is not None and VAR not in os.environ:
        want[VAR] = core
    if want and "numpy" in sys.modules:
        setting = " ".join(f"{k}={v}" for k, v in want.items())
        warnings.warn(f"numpy was imported before the project set {setting}: OpenBLAS chose "
                      f"its kernels and threads for this CPU, and results may differ in the "
                      f"last bits from other hosts (set {setting} in the environment)",
                      RuntimeWarning, stacklevel=3)
    os.environ.update(want)             # for this process's later loads and its children


def _loaded(what: str) -> dict:
    out = {}
    for mod, pattern, suffix in (("numpy", "numpy.libs/libscipy_openblas64_*.so", "64_"),
                                 ("scipy", "scipy.libs/libscipy_openblas-*.so", "")):
        if mod not in sys.modules:
            continue
        root = os.path.dirname(os.path.dirname(sys.modules[mod].__file__))
        for path in glob.glob(os.path.join(root, pattern)):
            try:
                fn = getattr(ctypes.CDLL(path), f"scipy_openblas_get_{what}{suffix}")
            except (OSError, AttributeError):
                continue
            if what == "corename":
                fn.restype = ctypes.c_char_p
                out[mod] = fn().decode()
            else:
                fn.restype = ctypes.c_int
                out[mod] = int(fn())
    return out


def loaded_cores() -> dict[str, str]:
    """The kernels OpenBLAS chose in this process, per loaded copy (numpy's, scipy's)."""
    return _loaded("corename")


def loaded_threads() -> dict[str, int]:
    """OpenBLAS's thread count in this process, per loaded copy (numpy's, scipy's)."""
    return _loaded("num_threads")
