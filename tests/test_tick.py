"""The compiled tick (firmware.tick) against the Python ECU it replaces (firmware.ecu with
its paths): the same outputs on every tick, the same DTC memory, over drives with faults of
every kind the inputs can carry; and the records' layout."""

import dataclasses

import numpy as np
import pytest

from calib.ecu_params import build
from calib.fx_tables import build_tables
from firmware import ecu as py_ecu
from firmware.diag import uds
from firmware.path import FixedPath
from firmware.tick import Ecu
from firmware.tick import ecu as tick_ecu
from firmware.tick.layout import params_record
from hil.config import default_vehicle
from hil.sil import ecu_params
from tests import golden
from tests.golden import ticks as per_tick

CFG = default_vehicle()
P = build(CFG)


def recorded_inputs(name: str) -> list:
    """The ECU's inputs of a golden scenario's drive, tick by tick (tests/golden/ticks)."""
    c = per_tick.load(name)

    def opt(v):
        return None if v < 0 else int(v)

    return [py_ecu.Inputs(int(c["tick"][k]), *(opt(c[n][k]) for n in (
        "body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")),
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
        names = ("body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")
        if k % 1500 == 700:                                  # a stuck channel, 400 ticks
            name = str(rng.choice(names[:4]))
            stuck = {name: (k + 400, d[name])}
        for name, (until, value) in list(stuck.items()):
            if k < until and value is not None:
                d[name] = value
        if rng.random() < 0.004:
            name = names[rng.integers(5)]
            d[name] = (None, 0, 4095, -3, 70000, 2.5, True, float("nan"))[rng.integers(8)]
        if rng.random() < 0.002:
            d["link_faults"] = int(rng.choice([1 << 10, 1 << 11, 1 << 12, 1 << 13, 1 << 5]))
        if k % 10 == 0 and rng.random() < 0.05:
            d["supply"] = int(rng.choice([0, 4095, 1200, 3900, 100]))
        if k % 100 == 50 and rng.random() < 0.3:
            d["req_kind"] = int(rng.integers(0, 5))
            d["req_mode"] = int(rng.integers(-1, 7))
            d["req_counter"] = int(rng.integers(0, 16))
        out.append(py_ecu.Inputs(**d))
    return out


def drive_both(params, inputs, fixed: bool):
    tables = build_tables(params) if fixed else None
    ref = py_ecu.init(params, FixedPath(params, tables, record=True) if fixed else None)
    new = Ecu(params, tables, record=fixed)
    for k, inp in enumerate(inputs):
        ref, want = py_ecu.step(ref, inp)
        got = new.step(inp)
        assert got == want, f"tick {k}: {got} != {want}"
        if fixed:
            assert new.log[-1] == ref.path.log[-1], f"tick {k}: the fixed-point hand-over"
    return ref, new


def assert_same_memory(ref, new):
    for i, (a, b) in enumerate(zip(ref.diag.dtc.entries, new.diag.dtc.entries, strict=True)):
        for f in ("status", "fdc", "passes", "occurrences", "aging", "first_tick",
                  "snapshot"):
            assert getattr(a, f) == getattr(b, f), (i, f)
    assert ref.diag.view == new.diag.view
    assert ref.akf.guard_hits == new.guard_hits


@pytest.mark.slow
@pytest.mark.parametrize("name,fixed,seed", [("comfort_b", False, 1), ("comfort_b", False, 2),
                                             ("fixed_point_auto", True, 3)])
def test_compiled_tick_equals_the_python_ecu_under_faults(name, fixed, seed):
    params = ecu_params(CFG, golden.BY_NAME[name].mode)
    bad = faulted(recorded_inputs(name)[:20000], seed)
    ref, new = drive_both(params, bad, fixed)
    assert_same_memory(ref, new)
    # the drive did reach the fault paths: DTCs confirmed, of the sensors' and the frames'
    confirmed = {tick_ecu.dtc.DTCS[i].name for i, e in enumerate(new.diag.dtc.entries)
                 if e.status & 0x08}
    assert len(confirmed) >= 5, confirmed


def test_reset_keeps_the_dtc_memory_and_starts_a_cycle():
    inputs = faulted(recorded_inputs("comfort_b")[:3000], 4)
    ref, new = drive_both(P, inputs, False)
    assert any(e.status & 0x08 for e in new.diag.dtc.entries)
    new.diag.session = 3
    assert uds.handle(new.diag, P, 3000, b"\x11\x01") == b"\x51\x01"
    assert new.diag.reset_requested == 1
    new.reset()
    ref = py_ecu.reset(ref, None)
    assert new.diag.session == 1 and not new.diag.reset_requested and new.tick == -1
    assert_same_memory(ref, new)
    for k, inp in enumerate(inputs[:500]):
        ref, want = py_ecu.step(ref, inp)
        assert new.step(inp) == want, k


def test_uds_reads_the_compiled_memory():
    """The UDS server reads and clears the record's DTC rows as it did the Python memory."""
    inputs = faulted(recorded_inputs("comfort_b")[:4000], 5)
    ref, new = drive_both(P, inputs, False)
    for req in (b"\x19\x0a", b"\x19\x02\xff", b"\x22\x01\x00\x01\x03\x01\x06\x01\x02",
                b"\x19\x01\x08"):
        assert uds.handle(new.diag, P, 4000, req) == uds.handle(ref.diag, P, 4000, req), req
    for i, e in enumerate(new.diag.dtc.entries):
        if e.snapshot is not None:
            code = tick_ecu.dtc.DTCS[i].code.to_bytes(3, "big")
            for sub in (b"\x04", b"\x06"):
                req = b"\x19" + sub + code + b"\xff"
                assert uds.handle(new.diag, P, 4000, req) == uds.handle(ref.diag, P, 4000,
                                                                          req)
    assert uds.handle(new.diag, P, 4000, b"\x14\xff\xff\xff") == b"\x54"
    assert all(e.status == 0x50 and e.snapshot is None for e in new.diag.dtc.entries)


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
    import subprocess
    import sys

    code = """
import json, hil
from numba import njit
from numba.core.runtime import rtsys
from hil import sil
from hil.config import default_vehicle
from calib.fx_tables import build_tables
from firmware.ecu import Inputs
from firmware.tick import Ecu
from firmware.tick import ecu as te

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
    import os

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
