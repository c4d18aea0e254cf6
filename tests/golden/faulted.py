"""Faulted drives of the ECU alone: a golden scenario's recorded inputs (``ticks/``) with
faults of every kind the inputs can carry, fed tick by tick to ``firmware.ecu.Ecu``; every
output, the fixed-point path's per-tick hand-over (the C parity record), the DTC memory and
the UDS server's answers at the end, pinned by digest in ``faulted.json``.

The golden traces drive fault-free; these drives reach the receive path's, the ADC's, the
model-based tests' and the DTC memory's fault branches that a fault-free drive never takes.

    python -m tests.golden.faulted            # check; exit 1 on a difference
    python -m tests.golden.faulted --update   # rewrite faulted.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import hil  # noqa: F401  (first: pins OpenBLAS's kernels before numpy loads)
import numpy as np
from firmware.ecu import Inputs

FILE = Path(__file__).resolve().parent / "faulted.json"
CHANNELS = ("body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")
# name: (golden scenario, fixed point, seed, ticks, reset at, ticks after the reset)
DRIVES = {
    "comfort_b_1": ("comfort_b", False, 1, 20000, None, 0),
    "comfort_b_2": ("comfort_b", False, 2, 20000, None, 0),
    "fixed_point_auto_3": ("fixed_point_auto", True, 3, 20000, None, 0),
    "comfort_b_reset_4": ("comfort_b", False, 4, 3000, 3000, 500),
}
# the UDS requests answered at the end: DTCs by status, DIDs, DTC count, and per confirmed
# DTC its snapshot and extended data (added by ``uds_answers``)
UDS_REQUESTS = (b"\x19\x0a", b"\x19\x02\xff", b"\x22\x01\x00\x01\x03\x01\x06\x01\x02",
                b"\x19\x01\x08")


def recorded_inputs(name: str) -> list:
    """The ECU's inputs of a golden scenario's drive, tick by tick (``tests/golden/ticks``)."""
    from tests.golden import ticks as per_tick

    c = per_tick.load(name)

    def opt(v):
        return None if v < 0 else int(v)

    return [Inputs(int(c["tick"][k]), *(opt(c[n][k]) for n in CHANNELS),
                   int(c["req_kind"][k]), int(c["req_mode"][k]), int(c["req_counter"][k]),
                   int(c["link_faults"][k]), opt(c["supply"][k])) for k in range(len(c["tick"]))]


def faulted(inputs: list, seed: int) -> list:
    """The inputs with faults of every kind the receive path and the sensors can give: a
    channel missing, at a rail, stuck, out of range or not an int; a supply sample low, high
    or clipped; link-fault bits; driver requests of every kind (and invalid ones)."""
    rng = np.random.default_rng(seed)
    out = []
    stuck = {}
    for inp in inputs:
        d = inp._asdict()
        k = inp.tick
        if k % 1500 == 700:                                  # a stuck channel, 400 ticks
            name = str(rng.choice(CHANNELS[:4]))
            stuck = {name: (k + 400, d[name])}
        for name, (until, value) in list(stuck.items()):
            if k < until and value is not None:
                d[name] = value
        if rng.random() < 0.004:
            name = CHANNELS[rng.integers(5)]
            d[name] = (None, 0, 4095, -3, 70000, 2.5, True, float("nan"))[rng.integers(8)]
        if rng.random() < 0.002:
            d["link_faults"] = int(rng.choice([1 << 10, 1 << 11, 1 << 12, 1 << 13, 1 << 5]))
        if k % 10 == 0 and rng.random() < 0.05:
            d["supply"] = int(rng.choice([0, 4095, 1200, 3900, 100]))
        if k % 100 == 50 and rng.random() < 0.3:
            d["req_kind"] = int(rng.integers(0, 5))
            d["req_mode"] = int(rng.integers(-1, 7))
            d["req_counter"] = int(rng.integers(0, 16))
        out.append(Inputs(**d))
    return out


def memory(ecu) -> list:
    """The DTC memory's rows, the last tick's view and the guard's count, as plain values."""
    rows = [[getattr(e, f) for f in ("status", "fdc", "passes", "occurrences", "aging",
                                     "first_tick")] + [list(e.snapshot or ())]
            for e in ecu.diag.dtc.entries]
    return [rows, list(ecu.diag.view), ecu.guard_hits]


def uds_answers(ecu, params, tick: int) -> list[bytes]:
    """The UDS server's answers on the ECU's memory: ``UDS_REQUESTS``, then each stored
    snapshot's and extended data record's read."""
    from firmware.diag import uds
    from firmware.diag.dtc import DTCS

    reqs = list(UDS_REQUESTS)
    for i, e in enumerate(ecu.diag.dtc.entries):
        if e.snapshot is not None:
            code = DTCS[i].code.to_bytes(3, "big")
            reqs += [b"\x19\x04" + code + b"\xff", b"\x19\x06" + code + b"\xff"]
    return [uds.handle(ecu.diag, params, tick, r) or b"" for r in reqs]


# the hand-over's fields the digests were pinned over (TickIn since gained the covariance
# side's inputs and gain, q_road, cov_flags, k_f: tests/test_c_parity.py checks those bit for
# bit against the C estimator)
PINNED_FIELDS = ("counts", "k_q", "r_q", "want", "passive", "fault", "regen", "reset")


def _hand_over_repr(tin, out) -> str:
    fields = ", ".join(f"{f}={getattr(tin, f)!r}" for f in PINNED_FIELDS)
    return f"(TickIn({fields}), {out!r})"     # (the repr of the (TickIn, outputs) pair)


def drive(name: str) -> dict:
    """One of ``DRIVES``: its digests and what it reached (the confirmed DTCs)."""
    from calib.fx_tables import build_tables
    from firmware.ecu import Ecu
    from firmware.diag.dtc import DTCS
    from hil.config import default_vehicle
    from hil.nodes.sil import ecu_params
    from tests import golden

    scenario, fixed, seed, n, reset_at, after = DRIVES[name]
    params = ecu_params(default_vehicle(), golden.BY_NAME[scenario].mode)
    ecu = Ecu(params, build_tables(params) if fixed else None, record=fixed)
    inputs = faulted(recorded_inputs(scenario)[:n], seed)
    h = hashlib.sha256()
    for inp in inputs:
        h.update(repr(tuple(ecu.step(inp))).encode())
        if fixed:
            h.update(_hand_over_repr(*ecu.log[-1]).encode())
            ecu.log.clear()
    res = {"outputs_sha256": h.hexdigest()}
    if reset_at is not None:
        from firmware.diag import uds

        ecu.diag.session = 3
        res["reset_answer"] = uds.handle(ecu.diag, params, reset_at, b"\x11\x01").hex()
        ecu.reset()
        res["after_reset"] = [ecu.diag.session, ecu.diag.reset_requested, ecu.tick]
        h = hashlib.sha256()
        for inp in inputs[:after]:
            h.update(repr(tuple(ecu.step(inp))).encode())
        res["after_reset_sha256"] = h.hexdigest()
    res["memory_sha256"] = hashlib.sha256(repr(memory(ecu)).encode()).hexdigest()
    res["uds_sha256"] = hashlib.sha256(b"|".join(uds_answers(ecu, params, n))).hexdigest()
    res["confirmed"] = sorted(DTCS[i].name for i, e in enumerate(ecu.diag.dtc.entries)
                              if e.status & 0x08)
    return res


def load() -> dict:
    return json.loads(FILE.read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.golden.faulted", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--update", action="store_true", help="rewrite faulted.json")
    ap.add_argument("names", nargs="*", help=f"drives (default: all): {', '.join(DRIVES)}")
    args = ap.parse_args(argv)
    unknown = set(args.names) - set(DRIVES)
    if unknown or (args.update and args.names):
        print(f"error: unknown drive(s): {', '.join(sorted(unknown))}" if unknown
              else "error: --update rewrites every drive", file=sys.stderr)
        return 2
    want = load() if FILE.exists() else {}
    got, bad = {}, 0
    for name in args.names or DRIVES:
        got[name] = drive(name)
        same = want.get(name) == got[name]
        bad += not same
        print(f"{name:22s} {'ok' if same else ('updated' if args.update else 'DIFFERS')}")
        if not same and not args.update and name in want:
            for k in got[name]:
                if got[name][k] != want[name].get(k):
                    print(f"    {k}: {want[name].get(k)} -> {got[name][k]}")
    if args.update:
        FILE.write_text(json.dumps(got, indent=1) + "\n")
        print(f"wrote {FILE}")
        return 0
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
