"""The same calibration bytes whatever kernels the host's libraries choose (issue 60).

OpenBLAS picks its kernels for the CPU (``Prescott``: SSE3, ``Sandybridge``: AVX, ``Haswell``:
AVX2 and FMA, ``SkylakeX``: AVX-512), and numpy vectorises exp and log differently with and
without AVX-512; each sums in its own order. Every x86-64 host can run the first three, so
this host designs each shipped vehicle afresh under each of them (no design cache, never the
committed data) and requires the very bytes of the committed calibration (``python -m
tools.calibration --check``) and of the committed C tables and A2L (``python -m tools.tables
--check``). Where the CPU has AVX-512 one more run turns numpy's AVX-512 paths off, as on a
host without them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from calib.blas import _cpu_flags

ROOT = Path(__file__).resolve().parents[1]
# the kernels and the CPU flags each needs
CORES = {"Prescott": {"pni"}, "Sandybridge": {"avx"}, "Haswell": {"avx2", "fma"}}   # (pni: SSE3)
NO_AVX512 = "X86_V4 AVX512_ICL AVX512_SPR"      # numpy's AVX-512 dispatch targets


def variants() -> list[tuple[str, dict]]:
    flags = _cpu_flags()
    out = [(core, {"OPENBLAS_CORETYPE": core}) for core, need in CORES.items() if need <= flags]
    if "avx512f" in flags:
        out.append(("Haswell, numpy without AVX-512",
                    {"OPENBLAS_CORETYPE": "Haswell", "NPY_DISABLE_CPU_FEATURES": NO_AVX512}))
    return out


def _run(env_extra: dict, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, **env_extra, "SUSPENSION_NO_CACHE": "1", "SUSPENSION_NO_DATA": "1",
           "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, env=env, text=True,
                          capture_output=True, timeout=900)


def _check(variant: tuple[str, dict]) -> tuple[str, subprocess.CompletedProcess,
                                               subprocess.CompletedProcess]:
    name, env = variant
    return (name, _run(env, "tools.calibration", "--check", "--json"),
            _run(env, "tools.tables", "--check", "--json"))


@pytest.mark.slow
def test_every_kernel_designs_the_committed_calibration_to_the_byte():
    runs = variants()
    assert len(runs) >= 3, f"this x86-64 CPU runs only {[n for n, _ in runs]}"
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(_check, runs))
    problems = []
    for name, cal, tab in results:
        if cal.returncode not in (0, 1) or not cal.stdout.strip():
            problems.append(f"{name}: tools.calibration exited {cal.returncode}: "
                            f"{cal.stderr.strip()[-400:]}")
            continue
        rep = json.loads(cal.stdout)
        for row in rep["vehicles"]:
            if row["state"] != "identical":
                moved = ", ".join(f"{m['path']}[{m['index']}] {m['committed']!r} -> "
                                  f"{m['fresh']!r}" for m in row["moved"][:5])
                problems.append(f"{name}: {row['vehicle']}: {row['state']} ({moved})")
        if tab.returncode != 0:
            differs = json.loads(tab.stdout)["differs"] if tab.stdout.strip() else tab.stderr
            problems.append(f"{name}: tools.tables --check: {differs}")
    assert not problems, "\n".join(problems)
