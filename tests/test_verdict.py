"""Every run's verdict: the checks fail on what went wrong, and JUnit readers parse them."""

import copy
import json
import subprocess
import sys
from pathlib import Path

import xml.etree.ElementTree as ET

import junitparser
import pytest

from hil.config import default_vehicle
from hil.nodes.sil import run
from hil.report import verdict
from hil.sim.road import load_route

ROOT = Path(__file__).resolve().parents[1]
B20 = str(ROOT / "tests" / "golden" / "routes" / "b20.toml")


@pytest.fixture(scope="module")
def clean():
    report, _ = run(default_vehicle(), load_route(B20), "comfort", 1, duration_s=4.0)
    return report


def _again(report, **over):
    """The checks of ``report`` recomputed with some inputs changed."""
    args = dict(expected_ticks=4000, dt_s=0.001, ticks={"PLANT": 4000, "ECU": 4000},
                bus_frames={}, fault_ticks=0)
    for name, n in ((k, v) for node in report["frames_sent"].values() for k, v in node.items()):
        args["bus_frames"][name] = args["bus_frames"].get(name, 0) + n
    args.update(over)
    return verdict.run_checks(report, **args)


def _failed(checks):
    return {c.name for c in checks if not c.ok}


def test_a_clean_run_passes_every_check(clean):
    assert clean["verdict"] == "pass" and verdict.exit_code(clean) == 0
    names = {c["name"] for c in clean["checks"]}
    assert {"ticks.PLANT", "ticks.ECU", "span_s", "bus.ACTUATOR_CMD", "app.answers",
            "frame_faults", "failsafe_ticks", "plant_fallback_ticks"} <= names
    assert _failed(_again(clean)) == set()


def test_each_check_fails_on_its_fault(clean):
    # a node that stopped early, a report of another span, a frame lost from the log
    assert _failed(_again(clean, ticks={"PLANT": 4000, "ECU": 3999})) == {"ticks.ECU"}
    assert _failed(_again(clean, expected_ticks=5000)) == {"ticks.PLANT", "ticks.ECU",
                                                            "span_s"}
    frames = {c.name[4:]: c.value for c in _again(clean) if c.name.startswith("bus.")}
    frames["PLANT_SENSORS"] -= 1
    assert _failed(_again(clean, bus_frames=frames)) == {"bus.PLANT_SENSORS"}
    # a fail-safe tick, a frame fault, a fallback tick: none allowed without injected faults
    assert _failed(_again(clean, fault_ticks=1)) == {"failsafe_ticks"}
    # a DTC confirmed in a drive without a fault: a false alarm that names a good part
    assert clean["dtcs_confirmed"] == []
    dtc = copy.deepcopy(clean)
    dtc["dtcs_confirmed"] = ["susp_defl_plausibility"]
    assert _failed(_again(dtc)) == {"dtcs_confirmed"}
    bad = copy.deepcopy(clean)
    bad["frame_faults"] = {"PLANT_SENSORS:checksum": 1}
    bad["plant_fallback_ticks"] = 2
    assert _failed(_again(bad)) == {"frame_faults", "plant_fallback_ticks"}
    # ...unless the faults were injected on purpose (the fault campaign judges those)
    assert _failed(_again(bad, injected=True, fault_ticks=9)) == set()
    # auto mode: no more switches than grade changes + 1
    chatty = dict(clean, mode="auto", mode_switches=5, grade_changes=3)
    assert _failed(_again(chatty)) == {"mode_switches"}
    assert verdict.verdict([]) == "fail"           # no checks is no pass


def test_realtime_limits_are_the_options(clean):
    rt = dict(pace="realtime", ticks={"PLANT": 4000}, missed_deadlines=40,
              lost_sensor_frames=4, fault_ticks=4)
    assert _failed(_again(clean, **rt)) == set()          # 1 % and 0.1 %: at the limits
    assert _failed(_again(clean, **dict(rt, missed_deadlines=41))) == {"missed_deadline_ratio"}
    assert _failed(_again(clean, **dict(rt, lost_sensor_frames=5))) == {"lost_frame_ratio"}
    tight = verdict.Limits(max_missed_ratio=0.0, max_lost_ratio=0.0)
    assert _failed(_again(clean, **rt, limits=tight)) == {
        "missed_deadline_ratio", "lost_frame_ratio", "failsafe_ratio"}


def test_junit_is_read_by_a_junit_reader(tmp_path, clean):
    checks = [verdict.Check(**c) for c in clean["checks"]]
    checks.append(verdict.check("mode_switches", 9, "<=", 4))
    path = verdict.write_junit(tmp_path / "j.xml", "hil sim b20 comfort", checks, 1.5)
    xml = junitparser.JUnitXml.fromfile(str(path))
    suites = list(xml) if isinstance(xml, junitparser.JUnitXml) else [xml]
    assert len(suites) == 1 and suites[0].name == "hil sim b20 comfort"
    cases = list(suites[0])
    assert [c.name for c in cases] == [c.name for c in checks]
    assert suites[0].tests == len(checks) and suites[0].failures == 1
    failed = [c for c in cases if not c.is_passed]
    assert [c.name for c in failed] == ["mode_switches"]
    assert "mode_switches = 9, want <= 4" in failed[0].result[0].message


def test_sim_cli_carries_the_verdict_in_json_junit_and_exit_code(tmp_path):
    junit = tmp_path / "sim.xml"
    proc = subprocess.run([sys.executable, "-m", "hil", "sim", "--route", B20, "--mode",
                           "comfort", "--duration", "4", "--json", "--junit", str(junit)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rep = json.loads(proc.stdout)
    assert rep["verdict"] == "pass"
    xml = junitparser.JUnitXml.fromfile(str(junit))
    cases = [c for s in xml for c in s]
    assert [c.name for c in cases] == [c["name"] for c in rep["checks"]]
    assert all(c.is_passed for c in cases)
    # the suite's time is the run's wall time; a check takes none of its own and says none
    # (not time="0" on every case)
    root = ET.parse(junit).getroot()
    assert float(root.find("testsuite").get("time")) > 0.0
    assert all(tc.get("time") is None for tc in root.iter("testcase"))


def test_a_fail_safe_episode_is_not_a_mode_switch_but_chatter_is():
    import numpy as np

    from firmware import safety
    from hil.nodes.sil import mode_switches

    mode = np.array([2, 2, 0, 0, 2, 2, 3, 3], dtype=np.int8)
    faults = np.zeros(8, dtype=np.int32)
    reason = np.zeros(8, dtype=np.int8)
    assert mode_switches(mode, faults, reason) == 3     # comfort -> passive -> comfort -> safety
    faults[2:4] = safety.FAULT_PLAUSIBILITY             # the passive ticks were a fail-safe
    assert mode_switches(mode, faults, reason) == 1
    faults[2:4] = safety.FAULT_RATE                     # not safety-relevant: a real switch
    assert mode_switches(mode, faults, reason) == 3


def test_the_road_holding_override_is_counted_apart_from_the_mode_switches():
    """Safety first: the override's safety mode is not the driver's mode changing (the
    comprehensive mode on a D road, overridden twice); its entries are counted on their own."""
    import numpy as np

    from firmware.modes import REASON_FAULT, REASON_ROAD_HOLDING
    from hil.nodes.sil import mode_switches, road_holding_entries

    mode = np.array([2, 4, 4, 3, 3, 4, 3, 3, 4, 4, 3], dtype=np.int8)
    reason = np.zeros(11, dtype=np.int8)
    faults = np.zeros(11, dtype=np.int32)
    assert mode_switches(mode, faults, reason) == 6 and road_holding_entries(reason) == 0
    reason[[3, 4, 6, 7]] = REASON_ROAD_HOLDING
    assert mode_switches(mode, faults, reason) == 2     # comfort -> comprehensive -> safety
    assert road_holding_entries(reason) == 2
    reason[10] = REASON_FAULT                           # (a fault is not the override)
    assert road_holding_entries(reason) == 2
    reason[0] = REASON_ROAD_HOLDING                     # from the first tick on: one entry
    assert road_holding_entries(reason) == 3


def test_a_run_whose_nodes_wrote_nothing_still_leaves_a_failing_report(tmp_path, capsys):
    """A bench that failed before any node wrote its record (the hub never opened, a node
    died at start) leaves report.json and report.md marked incomplete, verdict fail."""
    from hil.bench.runreport import partial_report
    from hil.bench.spec import RunSpec

    args = RunSpec(mode="comfort", seed=1, driver="accept", pace="lockstep",
                   junit=str(tmp_path / "j.xml"))
    partial_report(tmp_path, default_vehicle(), load_route(B20), args, 4000, 0.001, None,
                    "the CAN hub did not open its port")
    assert "could not write" not in capsys.readouterr().err
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["verdict"] == "fail" and rep["incomplete"] == "the CAN hub did not open its port"
    md = (tmp_path / "report.md").read_text()
    assert "INCOMPLETE" in md and "energy: not recorded" in md
    assert junitparser.JUnitXml.fromfile(args.junit).failures > 0


def test_the_verdict_text_names_the_confirmed_dtcs(clean, capsys):
    """A failing dtcs_confirmed check prints which DTCs, by name (a count names no part)."""
    dtc = copy.deepcopy(clean)
    dtc["dtcs_confirmed"] = ["body_accel_plausibility", "susp_defl_plausibility"]
    verdict.attach(dtc, _again(dtc))
    verdict.render(dtc)
    out = capsys.readouterr().out
    assert "FAIL dtcs_confirmed = 2" in out
    assert "confirmed DTCs: body_accel_plausibility, susp_defl_plausibility" in out
    verdict.render(clean)
    assert "confirmed DTCs" not in capsys.readouterr().out
