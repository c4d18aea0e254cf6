"""The compiled tick (firmware) under faults of every kind its inputs can carry: the
faulted drives of ``tests/golden/faulted.py`` against their pinned digests (every output,
the fixed-point hand-over, the DTC memory, UDS answers; pinned from the Python ECU the
compiled tick replaced, which gave the same digests), interpreted against compiled; and the
records' layout."""

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calib.ecu_params import build
from calib.fx_tables import build_tables
from firmware import ecu as tick_ecu
from firmware.diag import uds
from firmware.ecu import Inputs
from firmware.ecu import Ecu
from firmware.layout import params_record
from hil.config import default_vehicle
from tests.golden import faulted

ROOT = Path(__file__).resolve().parents[1]
CFG = default_vehicle()
P = build(CFG)
LONG = [n for n, d in faulted.DRIVES.items() if d[3] >= 20000]


@pytest.mark.slow
@pytest.mark.parametrize("name", LONG)
def test_faulted_drive_gives_its_pinned_digests(name):
    got = faulted.drive(name)
    assert got == faulted.load()[name], "python -m tests.golden.faulted shows what differs"
    # the drive did reach the fault paths: DTCs confirmed, of the sensors' and the frames'
    assert len(got["confirmed"]) >= 15, got["confirmed"]


def test_reset_keeps_the_dtc_memory_and_starts_a_cycle():
    """A UDS ECU reset (0x11 01) mid-drive: the state starts again (session default, tick
    -1), the DTC memory stays, the drive after it is pinned too."""
    got = faulted.drive("comfort_b_reset_4")
    assert got["reset_answer"] == "5101" and got["after_reset"] == [1, 0, -1]
    assert got == faulted.load()["comfort_b_reset_4"]


def test_interpreted_faulted_drive_equals_the_compiled():
    """The same source by the interpreter (NUMBA_DISABLE_JIT=1) on a faulted drive with a
    reset: the pinned digests (the compiled run gives them above)."""
    res = subprocess.run([sys.executable, "-m", "tests.golden.faulted", "comfort_b_reset_4"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600,
                         env=dict(os.environ, NUMBA_DISABLE_JIT="1"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]


def test_uds_reads_the_compiled_memory():
    """The UDS server reads the record's DTC rows (status by mask, count, snapshots) and a
    clear resets them to the status after a clear."""
    e = Ecu(P)
    inputs = faulted.faulted(faulted.recorded_inputs("comfort_b")[:4000], 5)
    for inp in inputs:
        e.step(inp)
    entries = list(e.diag.dtc.entries)
    confirmed = {tick_ecu.dtc.DTCS[i].code: en.status for i, en in enumerate(entries)
                 if en.status & 0x08}
    assert len(confirmed) >= 5, confirmed
    ans = uds.handle(e.diag, P, 4000, b"\x19\x02\x08")
    assert ans[:3] == b"\x59\x02\xff"
    got = {int.from_bytes(ans[i:i + 3], "big"): ans[i + 3] for i in range(3, len(ans), 4)}
    assert got == confirmed
    assert uds.handle(e.diag, P, 4000, b"\x19\x01\x08")[3:] == bytes([0x01, 0x00,
                                                                       len(confirmed)])
    for i, en in enumerate(entries):
        if en.snapshot is not None:
            code = tick_ecu.dtc.DTCS[i].code.to_bytes(3, "big")
            ans = uds.handle(e.diag, P, 4000, b"\x19\x04" + code + b"\xff")
            assert ans[:6] == b"\x59\x04" + code + bytes([en.status])
            assert ans[6:10] == b"\x01\x01\x02\x00"           # record 1, DID 0x0200
            assert int.from_bytes(ans[10:14], "big") == en.snapshot.tick
    assert uds.handle(e.diag, P, 4000, b"\x14\xff\xff\xff") == b"\x54"
    assert all(en.status == 0x50 and en.snapshot is None for en in e.diag.dtc.entries)


def test_no_record_field_is_shadowed_by_a_numpy_method():
    """The interpreter (NUMBA_DISABLE_JIT=1) reads a field as an attribute of numpy's
    ``record``, whose own attributes (``clip``, ``view``, ``sum``...) would win."""
    taken = set(dir(np.record))

    def names(dt, path):
        for n in dt.names or ():
            yield path + n, n
            sub = dt[n].base if dt[n].subdtype else dt[n]
            yield from names(sub, path + n + ".")

    for dt in (params_record(P).dtype, params_record(build_tables(P)).dtype,
               tick_ecu.state_dtype(P), tick_ecu.INPUTS, tick_ecu.OUTPUTS):
        clash = [p for p, n in names(dt, "") if n in taken]
        assert not clash, clash


def test_calibration_record_holds_every_number_of_the_calibration():
    rec = params_record(P)[0]
    assert rec["dt_s"] == P.dt_s
    assert (rec["akf"]["phi"] == P.akf.phi).all()
    assert tuple(rec["modes"]["controllers"]) == P.modes.controllers
    assert rec["adc"]["lsb"][2] == P.adc.susp_defl.lsb
    assert rec["fdi"]["cur_var"] == P.fdi.cur_sigma_a ** 2
    with pytest.raises(ValueError):
        params_record(P)[0]["dt_s"] = 0.5
    # a calibration whose tyre cannot lift off: gamma_wheel None reads as zeros
    p = dataclasses.replace(P, akf=dataclasses.replace(P.akf, gamma_wheel=None))
    assert (params_record(p)[0]["akf"]["gamma_wheel"] == 0).all()



def test_the_tick_allocates_nothing():
    """numba's allocation counters (NUMBA_NRT_STATS=1, in a child process) around a compiled
    loop of the tick: one tick and a thousand make the same allocations (those of the
    loop's own arguments), on both paths."""
    code = """
import json, hil
from numba import njit
from numba.core.runtime import rtsys
from hil.nodes import sil
from hil.config import default_vehicle
from calib.fx_tables import build_tables
from firmware.ecu import Inputs
from firmware.ecu import Ecu
from firmware import ecu as te

@njit
def run(P, T, S, I, O, n):
    for k in range(n):
        I[0].tick = k
        te.tick(P, T, S, I, O)

out = {}
p = sil.ecu_params(default_vehicle(), "comfort")
for name, tables in (("float", None), ("fixed", build_tables(p))):
    e = Ecu(p, tables)
    for k in range(3000):            # (past the settling: every test and controller runs)
        e.step(Inputs(k, 2048 + k % 7, 2040 + k % 11, 2048 - k % 5, 2048 + k % 3, 2000,
                      supply=2500 if k % 10 == 0 else None))
    counts = []
    for n in (1, 1000):
        a = rtsys.get_allocation_stats()
        run(e.P, e.T, e.S, e.I, e.O, n)
        b = rtsys.get_allocation_stats()
        counts.append([b.alloc - a.alloc, b.free - a.free])
    out[name] = counts
print(json.dumps(out))
"""
    import json

    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "NUMBA_NRT_STATS": "1"}, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout)
    for name, (one, many) in got.items():
        assert one == many, (name, one, many)     # no tick allocates
        assert one[0] == one[1]                   # and what the call allocated, it freed


def test_every_ecu_of_a_process_shares_its_layouts_dtype_objects():
    """numba reads an argument's type from its dtype object, fast only for one it has seen:
    a second ECU in a process (a campaign worker's next case) must reuse the first's dtype
    objects (``layout.canonical``), or each of its ticks takes the slow path (18 us against
    3.2 measured by tools.bench's step timer)."""
    tables = build_tables(P)
    a, b = Ecu(P, tables), Ecu(build(CFG), tables)
    for name in ("P", "T", "S", "I", "O"):
        assert getattr(a, name).dtype is getattr(b, name).dtype, name
