"""Compile the bench's numba code into its cache before a suite or a run needs it
(``make jit``; ``make test`` and ``make run`` start with it).

The compiled tick (``firmware``) takes most of a minute to compile on these machines
(the float and fixed-point variants, each with every stage inlined), and loads from numba's
cache in tens of milliseconds after that (``calib.jitcache`` keys the cache by the compiled
sources). Without this step every process that starts cold compiles it itself: the two test
workers, every node process of a ``hil run``. Here the variants compile side by side in
child processes, each driving a second of ``hil sim`` (the compiled SIL loop) or warming up
the nodes of ``hil run``; then the cache holds what every later process loads.

    python -m tools.jit [--json]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from hil.cli import add_json_argument, emit

ROOT = Path(__file__).resolve().parents[1]
# a second of hil sim per variant (the compiled SIL loop with the tick, the plant, the sensors,
# the road, the report), and the bench's nodes frame by frame (hil run's processes)
HIL_SIM = ["-m", "hil", "sim", "--route", "full_road_section", "--duration", "1", "--json"]
VARIANTS = {
    "float": [*HIL_SIM, "--mode", "auto"],
    "fixed": [*HIL_SIM, "--mode", "auto", "--fixed-point"],
    "nodes": ["-c", "import tools.jit as j; j.nodes()"],
}


def nodes() -> None:
    """The nodes of ``hil run`` warmed up (``hil.nodes.warm_up``: the ECU's tick called
    from Python, on both paths; the plant's step and sensors)."""
    from calib.fx_tables import build_tables
    from hil.transport import secoc
    from hil.nodes import sil
    from hil.transport.codec import Codec
    from hil.config import default_vehicle
    from hil.nodes import EcuNode, PlantNode, warm_up
    from hil.sim.road import load_route

    cfg, codec, key = default_vehicle(), Codec(), secoc.new_key()
    p = sil.ecu_params(cfg, "auto")
    build_tables(p)
    for fixed in (False, True):
        warm_up(EcuNode(p, codec, fixed_point=fixed, key=key))
    warm_up(PlantNode(cfg, load_route("full_road_section"), 0, codec, key=key))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.jit", description=__doc__.split("\n")[0])
    add_json_argument(ap)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    procs = {}
    for name, args_ in VARIANTS.items():
        cmd = [sys.executable, *args_]
        procs[name] = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL,
                                       stderr=subprocess.PIPE, text=True)
    failed = {}
    for name, p in procs.items():
        _, err = p.communicate()
        if p.returncode != 0:
            failed[name] = err.strip().splitlines()[-1:] if err.strip() else [str(p.returncode)]
    result = {"cache": os.environ.get("NUMBA_CACHE_DIR", ""), "variants": list(VARIANTS),
              "wall_s": round(time.perf_counter() - t0, 1), "failed": failed}
    emit(result, args.json, lambda r: print(
        f"numba cache {r['cache']}: {', '.join(r['variants'])} in {r['wall_s']} s"
        + (f"; FAILED {r['failed']}" if r["failed"] else "")))
    return 1 if failed else 0


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
