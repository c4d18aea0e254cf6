"""The same bytes on every x86-64 host: pin OpenBLAS's kernels before numpy loads.

numpy and scipy call OpenBLAS, which picks its kernels for the CPU when the library loads
(``Haswell`` for AVX2, ``SkylakeX`` for AVX-512, ...). The kernels sum in different orders,
so the design computed on an AVX-512 host (the ECU calibration: discretised AKF model, LQR
gains) differed from an AVX2 host's in the last bits: the committed C tables no longer
matched the generator, and the C fixed-point path (built from the committed tables) parted
from Python's by 1 LSB at tick 42417 of the full road section. With the kernels pinned to
``Haswell`` wherever the CPU has AVX2 and FMA, both hosts give the same bytes.

OpenBLAS reads ``OPENBLAS_CORETYPE`` when it loads, so :func:`pin` runs when ``hil`` is
imported: ``tools`` and the test suite (``tests/conftest.py``) import ``hil`` first, and
``firmware`` stays free of host matters (DESIGN.md §2). It keeps a value already in the
environment (an explicit choice), does nothing on a CPU without AVX2 and FMA or off x86-64
(those hosts may differ in the last bits), and warns when numpy was imported before it,
since the kernels are chosen by then. Child processes inherit the variable.
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
    if VAR in os.environ:
        return
    core = wanted_core()
    if core is None:
        return
    if "numpy" in sys.modules:
        warnings.warn(f"numpy was imported before the project set {VAR}={core}: OpenBLAS "
                      f"chose its kernels for this CPU, and results may differ in the last "
                      f"bits from other hosts (set {VAR}={core} in the environment)",
                      RuntimeWarning, stacklevel=3)
    os.environ[VAR] = core              # for this process's later loads and its children


def loaded_cores() -> dict[str, str]:
    """The kernels OpenBLAS chose in this process, per loaded copy (numpy's, scipy's)."""
    out = {}
    for mod, pattern, symbol in (
            ("numpy", "numpy.libs/libscipy_openblas64_*.so", "scipy_openblas_get_corename64_"),
            ("scipy", "scipy.libs/libscipy_openblas-*.so", "scipy_openblas_get_corename")):
        if mod not in sys.modules:
            continue
        root = os.path.dirname(os.path.dirname(sys.modules[mod].__file__))
        for path in glob.glob(os.path.join(root, pattern)):
            try:
                fn = getattr(ctypes.CDLL(path), symbol)
            except (OSError, AttributeError):
                continue
            fn.restype = ctypes.c_char_p
            out[mod] = fn().decode()
    return out
