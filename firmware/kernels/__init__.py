"""The compiled numeric kernels' decorator: numba's ``njit`` with the project's settings.

Kernels are plain Python over numpy arrays and floats, written as explicit loops in a fixed
order (no BLAS, whose summation order depends on the CPU), so the compiled code and the same
source run by the interpreter give the same bits: IEEE double arithmetic, no fast-math, no
fused multiply-add (``tests/test_jit.py`` runs the SIL both ways and compares the trace
hashes). ``NUMBA_DISABLE_JIT=1`` runs every kernel in the interpreter.

- ``cache=True``: the machine code is kept beside the source (``__pycache__``), so only the
  first process after a change compiles;
- ``error_model="numpy"``: a division by zero gives inf/NaN as in numpy (the callers' NaN
  checks react) instead of raising.
"""

from __future__ import annotations

import numba


def njit(fn):
    return numba.njit(cache=True, error_model="numpy", fastmath=False)(fn)


_TYPES = ("int32", "int64", "uint64", "voidptr")


def external(name: str, restype: str, *argtypes: str):
    """A C function that compiled code calls by its symbol (``numba.types.ExternalFunction``:
    the symbol is resolved when the machine code is loaded, so a cached kernel that calls it
    stays cacheable, unlike a ctypes function pointer). Types by name: ``_TYPES``."""
    from numba import types

    sig = getattr(types, restype)(*(getattr(types, t) for t in argtypes))
    if not {restype, *argtypes} <= set(_TYPES):
        raise ValueError(f"{name}: types are {_TYPES}")
    return types.ExternalFunction(name, sig)


def load_library(path: str) -> None:
    """Make a shared library's symbols visible to compiled code (``external``)."""
    import llvmlite.binding

    llvmlite.binding.load_library_permanently(path)


# NUMBA_DISABLE_JIT=1: the interpreter runs every kernel, and reads a record's fields as
# attributes only through numpy's recarray (firmware.layout)
INTERPRETED = bool(numba.config.DISABLE_JIT)
