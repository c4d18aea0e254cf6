"""Per-tick golden traces: the ECU trace itself, every tick's inputs and outputs as the trace
hash takes them (``hil.nodes.HASHED``), stored for a few short scenarios so that a change
shows as the first differing tick and field, not only as another hash.

A file (``tests/golden/ticks/NAME.ticks.xz``) is an xz stream of a one-line JSON header
(``{"fields": [[name, numpy dtype], ...], "ticks": N}``) and then each field's N values,
column after column, little-endian: columns compress far better than rows (most fields
change seldom). The bytes depend only on the trace (xz without a timestamp).
"""

from __future__ import annotations

import json
import lzma
from pathlib import Path

import numpy as np

from hil.nodes import HASHED

DIR = Path(__file__).resolve().parent / "ticks"
_CODES = {"q": "<i8", "i": "<i4", "I": "<u4", "B": "u1"}


def _dtype() -> np.dtype:
    """The packed row of ``HASHED`` as a structured dtype (the two reserved fields numbered)."""
    names, n = [], 0
    for name, _ in HASHED:
        if name == "reserved":
            name, n = f"reserved_{n}", n + 1
        names.append(name)
    return np.dtype({"names": names, "formats": [_CODES[c] for _, c in HASHED]})


DTYPE = _dtype()
assert DTYPE.itemsize == sum(np.dtype(_CODES[c]).itemsize for _, c in HASHED)


def path(name: str) -> Path:
    return DIR / f"{name}.ticks.xz"


def columns(packed: bytes) -> dict[str, np.ndarray]:
    """The packed rows of a run (``hil.nodes.sil.run(hashed=...)``) as one array per field."""
    rows = np.frombuffer(bytes(packed), dtype=DTYPE)
    return {name: np.ascontiguousarray(rows[name]) for name in DTYPE.names}


def encode(cols: dict[str, np.ndarray]) -> bytes:
    n = len(cols["tick"])
    header = {"fields": [[name, DTYPE[name].str] for name in DTYPE.names], "ticks": n}
    body = b"".join(np.ascontiguousarray(cols[name], DTYPE[name]).tobytes()
                    for name in DTYPE.names)
    return lzma.compress(json.dumps(header).encode() + b"\n" + body, preset=9)


def decode(blob: bytes) -> dict[str, np.ndarray]:
    raw = lzma.decompress(blob)
    line, body = raw.split(b"\n", 1)
    header = json.loads(line)
    n, cols, at = header["ticks"], {}, 0
    for name, dt in header["fields"]:
        size = n * np.dtype(dt).itemsize
        cols[name] = np.frombuffer(body[at:at + size], dtype=dt)
        at += size
    if at != len(body):
        raise ValueError(f"per-tick trace: {len(body) - at} bytes beyond its {n} ticks")
    return cols


def save(name: str, cols: dict[str, np.ndarray]) -> Path:
    DIR.mkdir(exist_ok=True)
    p = path(name)
    p.write_bytes(encode(cols))
    return p


def load(name: str) -> dict[str, np.ndarray]:
    return decode(path(name).read_bytes())


def differences(want: dict[str, np.ndarray], got: dict[str, np.ndarray],
                most: int = 12) -> list[str]:
    """Where two per-tick traces differ: the first differing tick, then per field (first
    differing first) its first tick with both values, how many ticks differ and the largest
    difference. Empty when they are the same."""
    out = []
    if list(want) != list(got):
        out.append(f"fields: want {list(want)}, got {list(got)}")
        return out
    n_w, n_g = len(want["tick"]), len(got["tick"])
    n = min(n_w, n_g)
    if n_w != n_g:
        out.append(f"ticks: want {n_w}, got {n_g} (compared over the first {n})")
    rows = []
    for name in want:
        a = want[name][:n].astype(np.int64)
        b = got[name][:n].astype(np.int64)
        bad = np.flatnonzero(a != b)
        if len(bad):
            i = int(bad[0])
            rows.append((i, f"{name}: first at tick {int(want['tick'][i])} (row {i}): want "
                            f"{int(a[i])}, got {int(b[i])}; {len(bad)} ticks differ, largest "
                            f"difference {int(np.max(np.abs(a[bad] - b[bad])))}"))
    rows.sort(key=lambda r: r[0])
    if rows:
        out.append(f"first differing tick: {int(want['tick'][rows[0][0]])}")
    out += [text for _, text in rows[:most]]
    if len(rows) > most:
        out.append(f"... and {len(rows) - most} more fields")
    return out
