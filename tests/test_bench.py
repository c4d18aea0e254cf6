"""The benchmark tool (make bench) produces every key of its contract."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.hil
def test_bench_tool_writes_every_key_of_the_contract(tmp_path):
    """``tools.bench --quick`` (short runs: checks the tool, its figures mean nothing)."""
    out = tmp_path / "bench.json"
    res = subprocess.run([sys.executable, "-m", "tools.bench", "--quick", "--json", "--out",
                          str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    data = json.loads(out.read_text())
    assert data == json.loads(res.stdout)
    for key in ("ecu_step_us_p50", "ecu_step_us_p99", "ecu_step_fixed_us_p50",
                "ecu_step_fixed_us_p99", "sil_rtf", "sil_tick_us", "c_core_tick_us",
                "c_core_tick_us_median", "sil_tick_over_c_core", "hil_sim_2s_wall_s",
                "hil_lockstep_rtf", "ga_tune_s"):
        assert isinstance(data[key], float) and math.isfinite(data[key]) and data[key] > 0.0, key
    assert data["ecu_step_us_p99"] >= data["ecu_step_us_p50"]
    assert data["ecu_step_fixed_us_p99"] >= data["ecu_step_fixed_us_p50"]
    assert data["sil_tick_over_c_core"] == data["sil_tick_us"] / data["c_core_tick_us"]
    assert data["c_core_tick_us_median"] >= data["c_core_tick_us"]
    assert data["c_core_ticks"] == 2000                       # --quick: a 2 s trace
    # the stages split the tick: the compiled loop took some of it, and they add up to it
    stages = data["sil_stage_us"]
    assert stages["sil_loop"] > 0.0, stages
    assert set(stages) >= {"sil_loop", "ecu_tick", "plant", "frames", "secoc", "nodes", "other"}
    # the realtime ratio is what the run counted: misses over its 3000 ticks (--quick: 3 s)
    rt = data["realtime"]
    assert data["realtime_missed_deadline_ratio"] == rt["missed_deadline_ratio"]
    assert rt["missed_deadline_ratio"] == rt["missed_deadlines"] / 3000
    # and with a UDS tester polling on the hub: it got answers
    rt = data["realtime_with_tester"]
    assert data["realtime_with_tester_missed_deadline_ratio"] == rt["missed_deadline_ratio"]
    assert rt["tester"]["requests"] > 10, rt["tester"]
    # the PIL figures: each target's largest tick is the largest of its traces' (make pil)
    if "skipped" not in data["pil"]:
        for name in ("m4f", "m7"):
            traces = data["pil"][name]["traces"].values()
            assert data[f"pil_{name}_tick_instructions_max"] == max(
                t["instructions"]["all"]["max"] for t in traces) > 1000
    # each goal's verdict is its comparison
    for key, goal in data["goals"].items():
        op, limit = goal["goal"].split()
        want = {"<=": data[key] <= float(limit), ">=": data[key] >= float(limit),
                "<": data[key] < float(limit)}[op]
        assert goal["met"] is want, key
    assert data["cpu_count"] >= 1 and data["cpu_model"]
    assert isinstance(data["blas_cores"], dict) and isinstance(data["blas_threads"], dict)
