"""The ride verdict of a drive (hil.validate.ride): a law that rides worse than passive fails
``hil sim``; each bound is the acceptance's own at the designs' window and widens only by
the scatter a shorter window adds; segments without a ride bound get no check."""

import json
import subprocess
import sys
from pathlib import Path

from calib.options import DesignOptions
from hil.config import default_vehicle
from hil.nodes import sil
from hil.sim.road import constant_route
from hil.validate import ride
from hil.validate.acceptance import ACCEPTANCE
from hil.validate.campaign.case import scored_window

ROOT = Path(__file__).resolve().parents[1]
CFG = default_vehicle()
C15 = str(ROOT / "tests" / "golden" / "routes" / "c15.toml")


def _sim(*args):
    p = subprocess.run([sys.executable, "-m", "hil", "sim", "--route", C15, "--mode", "safety",
                        "--seed", "1", "--json", *args], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    return p.returncode, json.loads(p.stdout)


def test_a_law_worse_than_passive_fails_the_ride_and_the_ecus_own_passes():
    code, rep = _sim("--controller", "pid")      # (the PID in safety mode: DTD over passive)
    assert rep["segments"][0]["ratio"]["dtd"] > 1.0
    bad = [c for c in rep["checks"] if not c["ok"]]
    assert code == 1 and rep["verdict"] == "fail"
    assert [c["name"] for c in bad] == ["ride.segment1.safety"] and bad[0]["value"] > 1.0
    row = rep["ride"][0]
    assert row["judged"] and not row["ok"]
    assert row["bounds"]["dtd"]["got"] > row["bounds"]["dtd"]["limit"]
    code, rep = _sim()
    assert code == 0 and rep["verdict"] == "pass"
    assert [c["name"] for c in rep["checks"] if c["name"].startswith("ride.")] == \
        ["ride.segment1.safety"]


def _report(mode, ratio, duration_s, grade="B"):
    return {"mode": mode, "duration_s": duration_s,
            "segments": [{"grade": grade, "speed_mps": 20.0, "scored": True, "ratio": ratio,
                          "modes": {mode: 1.0}}]}


def test_the_bound_widens_only_below_the_designs_window():
    P = sil.ecu_params(CFG, "comfort")
    opts = DesignOptions()
    ratio = {"ba": 0.8, "sws": 0.9, "dtd": 1.0}
    widened = {}
    for seconds in (opts.ratio_window_s, 20.0):
        route = constant_route("B", 20.0, seconds + 3.0)     # (3 s settle: the window)
        assert abs(scored_window(route, 0, None) - seconds) < 1e-9
        row = ride.judge(_report("comfort", ratio, None), CFG, route, P, opts)[0]
        assert row["judged"] and row["window_s"] == seconds
        assert {k: b["bound"] for k, b in row["bounds"].items()} == ACCEPTANCE["comfort"]
        widened[seconds] = {k: b["widened"] for k, b in row["bounds"].items()}
    assert all(abs(w) < 1e-12 for w in widened[opts.ratio_window_s].values())
    assert all(w > 0.0 for w in widened[20.0].values())
    # (the BA ratio's scatter over 20 s: a few per cent of the bound, not a free pass)
    assert 0.0 < widened[20.0]["ba"] < 0.15 * ACCEPTANCE["comfort"]["ba"]


def test_segments_without_a_ride_bound_get_no_check():
    P = sil.ecu_params(CFG, "auto")
    route = constant_route("A", 25.0, 30.0)
    rep = _report("regen", {"ba": 1.05, "sws": 1.0, "dtd": 1.05}, None, "A")
    rep["checks"] = []
    ride.attach(rep, CFG, route, P)
    assert rep["ride"][0]["judged"] is False and "regen" in rep["ride"][0]["why"]
    assert rep["checks"] == []
    mixed = _report("auto", {"ba": 2.0, "sws": 2.0, "dtd": 2.0}, None)
    mixed["segments"][0]["modes"] = {"comfort": 0.6, "safety": 0.4}
    assert ride.judge(mixed, CFG, route, P)[0]["why"] == "driven in mixed: no ride bound"
