"""The sensor campaign (hil.validate.sensorfaults, ``hil faults --sensors``): the plant's
persistent sensor faults, the same bytes on both SIL paths; the bank's open-bridge filters;
the filter's restart on a sensor out; the actuator test's current left alone; the judge and
the campaign on one car and seed."""

import json
import subprocess
import sys

import numpy as np
import pytest

from calib import fdi_bank as fb
from calib.ecu_params import build
from calib.options import DesignOptions
from firmware.diag import bank, degrade
from firmware.ecu import Ecu
from hil import nodes
from hil.config import default_vehicle
from hil.nodes import sil
from hil.sim.road import constant_route
from hil.sim.sensors import SensorSuite, to_counts
from hil.validate import sensorfaults as sf

CFG = default_vehicle()


def _counts(kind, size, ticks=400, onset=100):
    s = SensorSuite(CFG.sensors, np.random.default_rng(5))
    if kind:
        s.set_fault("body_accel", kind, onset, size)
    return np.array([s.sample(0.5, 0.0, 0.0, 0.0, 20.0, k) for k in range(ticks)])


def test_each_fault_kind_changes_the_counts_as_specified():
    lsb = CFG.sensors.body_accel.lsb
    clean = _counts(None, 0.0)
    assert (_counts("bias", 10 * lsb)[:, 0] - clean[:, 0]).tolist() == [0] * 100 + [10] * 300
    drift = _counts("drift", lsb)[:, 0] - clean[:, 0]           # one count per tick
    assert drift[100] == 0 and drift[150] == 50 and drift[399] == 299
    gain = _counts("gain", 1.0)[:, 0] - clean[:, 0]             # 0.5 m/s^2 more
    assert np.all(np.abs(gain[100:] - round(0.5 / lsb)) <= 1) and not gain[:100].any()
    stuck = _counts("stuck", 0.0)[:, 0]
    assert len(set(stuck[100:])) == 1 and stuck[100] == clean[100, 0]
    drop = _counts("dropout", 0.0)[:, 0]
    zero = to_counts(CFG.sensors.body_accel, 0.0)
    assert all(drop[k] == zero for k in range(100, 400) if (k - 100) % 100 < 5)
    assert all(drop[k] == clean[k, 0] for k in range(400) if k < 100 or (k - 100) % 100 >= 5)
    noisy = _counts("noise", 5.0)[:, 0] - round(0.5 / lsb)
    ratio = np.std(noisy[100:]) / np.std(clean[100:, 0] - round(0.5 / lsb))
    assert 4.0 < ratio < 6.0, ratio
    assert (_counts(None, 0.0)[:, 1:] == _counts("noise", 5.0)[:, 1:]).all()   # (one channel)
    with pytest.raises(ValueError):
        SensorSuite(CFG.sensors, np.random.default_rng(1)).set_fault("body_accel", "melt", 0)


@pytest.mark.parametrize("kind,size", [("bias", 0.2), ("stuck", 0.0), ("noise", 5.0)])
def test_a_sensor_fault_gives_the_same_bytes_compiled_and_node_by_node(kind, size):
    route = constant_route("B", 20.0, 60.0)
    runs = [sil.run(CFG, route, "comfort", 3, duration_s=2.5, compiled=c,
                    sensor_fault=("body_accel", kind, 1500, size))[0]["trace_sha256"]
            for c in (True, False)]
    assert runs[0] == runs[1]
    assert runs[0] != sil.run(CFG, route, "comfort", 3, duration_s=2.5)[0]["trace_sha256"]


def test_the_bank_holds_its_level_with_the_bridge_open():
    """Fault-free passive driving: each filter's statistic stays below its level (the filters
    with the driven bridge's gain sat above it, the WA-blind one at 1.1-1.2), and its open
    design's healthy mean is the designed 1 (0.9-1.1 over 10 s)."""
    stats = []
    tick = nodes.EcuNode.tick

    def spy(self):
        out = tick(self)
        stats.append(self.state.S["bank"][0]["stat"].copy())
        return out
    nodes.EcuNode.tick = spy
    try:
        sil.run(CFG, constant_route("B", 20.0, 300.0), "passive", 4, duration_s=12.0,
                compiled=False)
    finally:
        nodes.EcuNode.tick = tick
    s = np.array(stats[2000:])
    level = build(CFG).bank.level
    assert s.max() < level, (s.max(axis=0), level)
    assert np.all(np.abs(s.mean(axis=0) - 1.0) < 0.1), s.mean(axis=0)


def test_the_open_design_reads_no_current():
    """With the bridge open no current flows: the current a filter reads moves none of its
    states (its gain column is zero) and is its sensor's noise alone."""
    for name, g in fb.generators(CFG, DesignOptions(), bridge_open=True).items():
        if "current" in g.reads and g.phi.shape[0] == 5:
            j = g.reads.index("current")
            assert not g.K[:, j].any() and g.S_noise[j, j] == g.r0[j, j], name


def test_a_sensor_out_restarts_the_filter():
    """The entry drops what the faulty sensor left in the estimate: the filter starts again
    from its power-up state (the fixed-point path's restart flagged for C)."""
    ecu = Ecu(build(CFG))
    s = ecu.rec
    s.akf.x[:] = 0.3
    s.akf.P[:] *= 0.5
    degrade.enter(ecu.P[0], ecu.S[0], 0, 100)
    assert not s.akf.x.any() and np.array_equal(s.akf.P, ecu.P[0]["akf"]["p0"])
    assert s.fx.reset


def test_the_current_left_alone_beside_the_actuator_test_is_not_isolated():
    """The actuator test failed and only the filters that read the current are inconsistent:
    the current sensor or the actuator, not isolated; the current-blind filter inconsistent
    too (the force was wrong): the actuator, unless the current read was clipped at its rail
    (the city route's 75 % current gain named the actuator beside the current's circuit)."""
    P = build(CFG)
    for cleared, clipped, want in ((0b0111, False, bank.NOT_ISOLATED),
                                   (0b1111, False, bank.ACTUATOR_STUCK),
                                   (0b1111, True, bank.NOT_ISOLATED)):
        ecu = Ecu(P)
        B = ecu.rec.bank
        B.episode, B.decided, B.act, B.act_since, B.alone_since = 10, bank.NONE, 0, -1, -1
        B.cleared, B.above, B.cur_held = cleared, 0, False
        got = bank.NONE
        for t in range(11, 11 + P.bank.act_ticks + P.bank.confirm_ticks + 2):
            got = bank.decide(ecu.P[0], B, t, False, 0, bank.ACT_STUCK_BIT,
                              np.zeros(7, np.int64), clipped)
            if got != bank.NONE:
                break
        assert got == want, (cleared, clipped, got)


def _result(**over):
    r = {"name": "ba_bias_large", "vehicle": "table3.toml", "seed": 101, "kind": "bias",
         "magnitude": "large", "isolable": True, "isolation": "right", "dtcs": [],
         "detected_before_onset": 0, "detect_ms": 5.0, "expect_detect_ms": 2.0,
         "expect_isolate_ms": 1700.0, "command": "-"}
    r.update(over)
    return r


def test_the_judge():
    assert sf.problems(_result()) == []
    assert "wrong isolation" in sf.problems(_result(isolation="wrong", dtcs=["x"]))[0]
    assert sf.problems(_result(isolation="not isolated"))          # isolable, large
    assert not sf.problems(_result(isolation="not isolated", isolable=False))
    assert sf.problems(_result(detect_ms=201.0))                   # large: 200 ms
    assert not sf.problems(_result(detect_ms=1900.0, magnitude="small", kind="gain",
                                   isolable=False))               # small: 2 s
    assert not sf.problems(_result(detect_ms=None, expect_detect_ms=None, isolable=False))
    assert sf.problems(_result(detected_before_onset=3))
    doc = sf.summarise([_result(), _result(isolation="wrong", dtcs=["C1004-29 x"])])
    assert doc["verdict"] == "fail" and doc["wrong_isolations"] == 1


def test_the_campaign_on_one_car_and_seed(tmp_path):
    """``hil faults --sensors`` for the default car on held-out seed 101: every fault of the
    analysis driven, none named wrong, the verdict passes (the whole campaign, both cars
    and three seeds: docs/isolation.md)."""
    run = subprocess.run([sys.executable, "-m", "hil", "faults", "--sensors", "--vehicle",
                          "table3.toml", "--seeds", "101-101", "--out", str(tmp_path),
                          "--json"], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    doc = json.loads(run.stdout)
    assert doc["faults"] == 36 and doc["wrong_isolations"] == 0
    key = [r for r in doc["results"] if r["isolable"] and (
        r["magnitude"] == "large" or r["kind"] in ("bias", "stuck"))]
    assert len(key) >= 8 and all(r["isolation"] == "right" for r in key)
    assert doc["by_vehicle"]["table3.toml"]["right"] >= 25
    assert (tmp_path / "sensor-faults.md").read_text().startswith("## table3.toml")
