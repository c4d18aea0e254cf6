"""The compiled SIL loop (hil/kernels/silloop.py through hil/nodes/fastsil.py) against the nodes of
hil/nodes/ frame by frame (``sil.run(compiled=False)``): the same report, trace, frames on
the bus (every byte, in order) and node state afterwards; no allocation per tick."""

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from hil.config import default_vehicle, load_vehicle
from hil.nodes import fastsil, sil
from hil.nodes import AppNode, EcuNode, PlantNode
from hil.sim.road import load_route
from hil.transport.codec import Codec

CFG = default_vehicle()
KEY = bytes(range(16))


def _both(route, mode, seed, **kw):
    out = []
    for compiled in (False, True):
        frames, calls = [], []
        record = [] if kw.get("fixed_point") else None      # (the C parity record)
        rep, tr = sil.run(CFG if "cfg" not in kw else kw["cfg"], load_route(route), mode, seed,
                          key=KEY, compiled=compiled,
                          on_frame=lambda fid, data: frames.append((fid, data)),
                          progress=lambda done, total: calls.append((done, total)),
                          fx_record=record, **{k: v for k, v in kw.items() if k != "cfg"})
        out.append((rep, tr, frames, calls, record))
    return out


def _same(a, b):
    (ra, ta, fa, pa, xa), (rb, tb, fb, pb, xb) = a, b
    assert json.dumps(ra, default=str) == json.dumps(rb, default=str)
    assert fa == fb
    assert xa == xb and (xa is None or len(xa) == len(ta.segment))
    assert pa == pb and len(pa) >= 200          # (progress: the same calls)
    assert ta.arrays.keys() == tb.arrays.keys()
    for name in ta.arrays:
        assert np.array_equal(ta.arrays[name], tb.arrays[name], equal_nan=True), name
    assert np.array_equal(ta.segment, tb.segment)


@pytest.mark.parametrize("mode,kw", [
    ("auto", {"duration_s": 20.0}),                       # past one chunk (16,384 ticks)
    ("auto", {"duration_s": 6.0, "fixed_point": True}),
    ("comfort", {"duration_s": 4.0}),                     # the fixed policy: chooses, refuses
    ("auto", {"duration_s": 4.0, "policy": "refuse"}),
    ("auto", {"duration_s": 5.0, "noise_step": (2.0, 40.0)}),   # faults, road holding
    # a driver script (Python's app sends its entries, the calendar's spans): a choice, an
    # acceptance of what is recommended then, two at the same time, a refusal
    ("auto", {"duration_s": 6.0, "policy": "script",
              "script": [(0.5, "choose", 2), (1.2345, "accept", None), (3.0, "choose", 4),
                         (3.0, "choose", 3), (4.05, "refuse", None)]}),
])
def test_compiled_loop_is_the_nodes_frame_by_frame(mode, kw):
    a, b = _both("full_road_section", mode, 3, **kw)
    assert len(a[2]) > 1000
    _same(a, b)
    if kw.get("duration_s", 0) >= 20:       # the driver accepted a recommendation
        assert b[0]["driver"]["requests"] == {"accept": 1}
    if mode == "comfort":                   # the fixed policy chose its mode
        assert b[0]["driver"]["requests"]["choose"] == 1
    if kw.get("policy") == "script":        # every entry sent
        assert sum(b[0]["driver"]["requests"].values()) == 5


def test_noise_step_sets_faults_the_same_way():
    """A strong noise step: the fault word and the fail-safe come from the ECU's own
    diagnostics in the loop (not zero by luck)."""
    a, b = _both("full_road_section", "auto", 5, duration_s=5.0, noise_step=(1.0, 60.0))
    _same(a, b)
    assert np.count_nonzero(b[1].arrays["faults"]) > 0


def test_other_vehicle_and_route():
    cfg = load_vehicle("hil/vehicles/suv.toml")
    a, b = _both("city", "auto", 1, duration_s=3.0, cfg=cfg)
    _same(a, b)


def _upcoming(sens, m: int) -> list:
    """The sensors' next ``m`` noise values: what is left of their block, then their
    generator's (the loop draws larger blocks: where the generator stands differs)."""
    left = sens._noise[sens._next:].ravel()
    return np.concatenate([left, sens.rng.standard_normal(m)])[:m].tolist()


@pytest.mark.parametrize("n,python", [
    (2500, []),
    # Python's spans of the calendar: at the start, inside a noise block of 256 (and a supply
    # period), two that touch, one across the loop's chunk of 16,384, one to the end
    (17000, [(0, 3), (1001, 1057), (1057, 1060), (16380, 16390), (16900, 17000)]),
])
def test_nodes_state_after_the_loop(n, python):
    """The node objects hold what run_in_process leaves in them (a caller reads them), also
    when Python runs them in spans of the calendar and the loop takes them over again."""
    states = []
    for compiled in (False, True):
        codec = Codec()
        p = sil.ecu_params(CFG, "auto")
        plant = PlantNode(CFG, load_route("city"), 2, codec, key=KEY,
                          noise_step=(1.0, 30.0) if python else None)
        plant.n = n
        ecu_node = EcuNode(p, codec, lockstep=True, key=KEY)
        app = sil.app_node(codec, "auto", p.dt_s, key=KEY)
        frames, calls = [], []
        kw = {"on_frame": lambda fid, data: frames.append((fid, data)),
              "progress": lambda done, total: calls.append(done)}
        if compiled:
            assert fastsil.eligible(plant, ecu_node, app) is None
            bus = fastsil.run(plant, ecu_node, app, python=python, **kw)
        else:
            from hil.nodes import run_in_process
            bus = run_in_process(plant, ecu_node, app, **kw)
        if python:
            assert app.faults_seen                  # (the driver was told of a fault)
        states.append(json.dumps({
            "frames": hashlib.sha256(repr(frames).encode()).hexdigest(), "progress": calls,
            "twin": [plant.arrays[k].tolist() for k in sorted(plant.arrays)],
            "obs": plant.obs.tobytes().hex(), "rows": ecu_node.rows.tobytes().hex(),
            "noise": [_upcoming(plant.sensors, 3000), plant.supply.rng.standard_normal(3).tolist()],
            "ledger": plant.active._acc.tolist(), "log": app.log,
            "bus": bus, "plant": plant.summary(), "ecu": ecu_node.summary(),
            "app": app.summary(), "cmd": [plant.cmd, plant.cmd_tick, plant.cmd_seq],
            "x": plant.active.x.tolist(), "ecu_record": ecu_node.E.tobytes().hex(),
            "ecu_rx": ecu_node.RX.tobytes().hex(), "ecu_sec": ecu_node.SEC.tobytes().hex(),
            "ff": [ecu_node.ff.tolist(), ecu_node.ff_first.tolist()],
            "fv": [app.req_sec.fv, plant.cmd_auth.latest, plant.cmd_auth.rejected],
            "counters": [plant.tx.counters, app.tx.counters], "rx": vars(plant.cmd_rx),
            "ecu_k": ecu_node.k, "app_state": [app.t, app.kind, app.req_id, app._shown]},
            default=str))
    assert states[0] == states[1]


def test_runs_the_loop_does_not_cover_are_named():
    codec = Codec()
    p = sil.ecu_params(CFG, "auto")
    plant = PlantNode(CFG, load_route("city"), 2, codec, key=KEY)
    ecu_node = EcuNode(p, codec, key=KEY)
    app = AppNode(codec, "interactive", key=KEY)
    assert "interactive" in fastsil.eligible(plant, ecu_node, app)
    with pytest.raises(ValueError, match="does not cover"):
        fastsil.run(plant, ecu_node, app)
    auto = sil.app_node(codec, "auto", p.dt_s, key=KEY)
    assert "SecOC" in fastsil.eligible(plant, EcuNode(p, codec), auto)
    assert "keys" in fastsil.eligible(plant, EcuNode(p, codec, key=bytes(16)), auto)


def test_the_loop_allocates_nothing_per_tick():
    """numba's allocation counters (NUMBA_NRT_STATS=1, in a child process) around each call
    of the compiled loop: a run of 0.5 s and one of 12 s (one call each) allocate the same
    (the call's own scratch), and free what they allocate."""
    code = """
import json, hil
from numba.core.runtime import rtsys
from hil.nodes import sil
from hil.kernels import silloop as kl
from hil.config import default_vehicle
from hil.sim.road import load_route

inner = kl.run
counts = []
def counted(*args):
    a = rtsys.get_allocation_stats()
    out = inner(*args)
    b = rtsys.get_allocation_stats()
    counts.append([b.alloc - a.alloc, b.free - a.free])
    return out
kl.run = counted
for d in (0.5, 0.5, 12.0):
    for fx in (False, True):
        sil.run(default_vehicle(), load_route("full_road_section"), "auto", 3, duration_s=d,
                fixed_point=fx)
print(json.dumps(counts))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "NUMBA_NRT_STATS": "1"}, timeout=900)
    assert res.returncode == 0, res.stderr[-2000:]
    counts = json.loads(res.stdout)
    assert len(counts) == 6
    for short, long in ((counts[2], counts[4]), (counts[3], counts[5])):
        assert short == long, counts
        assert short[0] == short[1]
