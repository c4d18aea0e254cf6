"""Which of ``c/ecu_fx.c``'s branches the PIL traces exercise (``tools.pil``): the host build
with gcc's ``--coverage`` replays every trace, and ``gcov --json-format`` says, per line, how
often it ran and which of its branch edges were taken. The largest tick observed is a
measurement over these paths only: an untaken branch is a path whose cost no trace measured
(docs/pil.md)."""

from __future__ import annotations

import gzip
import json
import subprocess
from pathlib import Path

from tools.c_build import C_DIR, compile_c, replay_input, replay_sources


def coverage(runs, work: Path) -> dict:
    """``runs``: (tables directory, record) per trace. Branch edges and lines of ecu_fx.c
    that ran, and the lines that never did (with their text)."""
    counts = {}
    for k, (gen, rec) in enumerate(runs):
        d = work / f"cov{k}"
        d.mkdir(parents=True, exist_ok=True)
        exe = compile_c(d / "replay", replay_sources(gen), "--coverage", "-O0", gen=gen)
        subprocess.run([str(exe)], input=replay_input(rec), capture_output=True, text=True,
                       check=True, cwd=d)
        gcda = sorted(d.glob("*ecu_fx.gcda"))
        subprocess.run(["gcov", "--json-format", "--branch-probabilities", str(gcda[0])], cwd=d, capture_output=True,
                       check=True)
        data = json.loads(gzip.decompress(next(d.glob("*ecu_fx.gcov.json.gz")).read_bytes()))
        src = next(f for f in data["files"] if f["file"].endswith("ecu_fx.c"))
        for ln in src["lines"]:
            c = counts.setdefault(ln["line_number"], [0, []])
            c[0] += ln["count"]
            br = [b["count"] for b in ln.get("branches", [])]
            c[1] = [a + b for a, b in zip(c[1], br)] if c[1] else br
    text = (C_DIR / "ecu_fx.c").read_text().splitlines()
    edges = [b for _, br in counts.values() for b in br]
    never = sorted(n for n, (c, _) in counts.items() if c == 0)
    return {"lines": len(counts), "lines_run": len(counts) - len(never),
            "branch_edges": len(edges), "branch_edges_taken": sum(1 for b in edges if b),
            "lines_never_run": {n: text[n - 1].strip() for n in never}}
