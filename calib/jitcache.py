"""numba's cache, keyed by the compiled code's source (set up before numba loads).

numba keeps a compiled function beside its source (``cache=True``) and checks only that
file's time stamp: a function that calls functions of other files (the compiled tick,
``firmware.ecu.tick``, calls every stage) keeps their old machine code when only they
change. So the cache lives in a directory named by a digest of every source numba compiles
here (``firmware/``, whose constants are compiled in too, and ``hil/kernels/``): a change to
any of them starts an empty directory, a checkout whose sources are the same shares it.

``pin`` sets ``NUMBA_CACHE_DIR`` to ``BASE/numba/DIGEST`` (``BASE``: the design cache's
directory, ``calib.cache``; an explicit ``NUMBA_CACHE_DIR`` is the base instead) when
``calib`` is imported, before numba is: ``hil``, ``tools`` and the tests import it first. A
process that imports ``firmware`` alone gets numba's default (the ``__pycache__`` beside the
source, with the stale-caller problem above).
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = (ROOT / "firmware", ROOT / "hil" / "kernels")
VAR = "NUMBA_CACHE_DIR"
BASE_VAR = "SUSPENSION_NUMBA_BASE"     # (the base chosen, for the processes this one starts)


def digest() -> str:
    h = hashlib.sha256()
    for base in SOURCES:
        for p in sorted(base.rglob("*.py")):
            h.update(str(p.relative_to(ROOT)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def pin() -> None:
    if "numba" in sys.modules:
        return                          # (too late: numba read its configuration)
    from calib import cache

    base = os.environ.get(BASE_VAR) or os.environ.get(VAR) or str(cache.directory() / "numba")
    os.environ[BASE_VAR] = base
    os.environ[VAR] = str(Path(base) / digest()[:16])
