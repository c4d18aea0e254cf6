"""The bench as processes on the CAN hub (marker ``hil``): SIL = HIL, the log, the scenarios,
and what happens when a node dies or the user presses Ctrl-C."""

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from firmware import params as fp
from hil.nodes import ID
from hil.transport.buslog import SIL_CHANNEL, read_log, same_channel
from tests import golden
from tests.procutil import children as _children
from tests.procutil import cmdline as _cmdline
from tests.procutil import REALTIME_TIMING, assert_only_timing_failed

ROOT = Path(__file__).resolve().parents[1]
ROUTES = Path(__file__).resolve().parent / "routes"
START_CAP_S = 600
pytestmark = pytest.mark.hil


def hil_run(out: Path, *args, timeout=900) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", "run", "--out", str(out), "--json", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def without_bench(report: dict) -> dict:
    return {k: v for k, v in report.items() if k != "bench"}


def test_full_road_section_lockstep_equals_sil(tmp_path):
    """The acceptance run: full_road_section, auto, seed 1, lockstep over the hub."""
    proc = hil_run(tmp_path / "hil", "--route", "full_road_section", "--mode", "auto",
                   "--seed", "1", "--pace", "lockstep", "--key-file",
                   str(golden.key_file(tmp_path)),      # the golden runs' SecOC key
                   "--start-time", golden.START_TIME)   # ... and start
    assert proc.returncode == 0, proc.stderr[-2000:]
    hil_rep = json.loads(proc.stdout)
    # SIL = HIL: the same ECU trace hash, the same report and the same log, byte for byte, as
    # the SIL's golden trace of this scenario pins them (tests/test_golden.py runs the SIL)
    sil_gold = golden.load()["full_road_section_auto"]
    assert sil_gold["command"].startswith("python -m hil sim --route full_road_section "
                                          "--mode auto --seed 1 --key-file KEY "
                                          f"--start-time {golden.START_TIME} --out")
    assert hil_rep["trace_sha256"] == sil_gold["trace_sha256"]
    got = {k: v for k, v in without_bench(hil_rep).items()
           if k not in golden.IGNORED_REPORT_KEYS}
    assert golden.diff(sil_gold["report"], got) == []
    log = tmp_path / "hil" / "bus.log"
    # (the same bytes but for the channel: the hub's hub0 where the SIL writes sil0)
    assert log.read_text().startswith("(1767225600.000000) hub0 ")
    assert hashlib.sha256(same_channel(log.read_bytes(), SIL_CHANNEL)).hexdigest() == \
        sil_gold["buslog_sha256"]
    # every frame each node reports sending is in the log, and nothing else
    frames = read_log(log)
    sent = {name: n for node in hil_rep["frames_sent"].values() for name, n in node.items()}
    assert len(frames) == sum(sent.values()) == hil_rep["bench"]["frames_logged"]
    ids, counts = np.unique([f[1] for f in frames], return_counts=True)
    assert {int(i): int(c) for i, c in zip(ids, counts)} == {ID[n]: c for n, c in sent.items()}
    # the run itself: every tick commanded, grades right
    assert hil_rep["plant_missed_cmds"] == 0 and hil_rep["plant_fallback_ticks"] == 0
    assert hil_rep["grade_accuracy"] >= 0.95
    assert hil_rep["mode_switches"] <= hil_rep["grade_changes"] + 1
    for f in ("report.md", "timeseries.png", "modes.png", "road.png", "energy.png"):
        assert (tmp_path / "hil" / f).stat().st_size > 0
    # cantools decodes every frame of the log (SIM_TRUTH is in the DBC too)
    dec = subprocess.run([sys.executable, "-m", "cantools", "decode",
                          str(ROOT / "dbc" / "suspension.dbc")], stdin=open(log),
                         capture_output=True, text=True, timeout=300)
    assert dec.returncode == 0
    assert "Unknown frame id" not in dec.stdout
    assert dec.stdout.count("ACTUATOR_CMD(") == sent["ACTUATOR_CMD"]


def test_refusal_scenario_and_can_player(tmp_path):
    """A driver who chose comfort refuses every recommendation: the ECU recommends energy
    feedback on the A road and safety on the C road, and stays in comfort."""
    proc = hil_run(tmp_path, "--route", str(ROUTES / "refusal.toml"), "--mode", "comfort",
                   "--seed", "2")
    assert proc.returncode == 0, proc.stderr[-2000:]
    rep = json.loads(proc.stdout)
    assert rep["driver"]["policy"] == "fixed"
    assert rep["driver"]["requests"].get("refuse", 0) >= 2
    assert "accept" not in rep["driver"]["requests"]
    tr = np.load(tmp_path / "ecu.npz")
    mode, rec = tr["mode"], tr["recommended"]
    assert np.all(mode[1:] == fp.MODE_COMFORT)
    assert {fp.MODE_ENERGY, fp.MODE_SAFETY} <= set(np.unique(rec).tolist())
    # the refusals are on the bus: DRIVER_REQUEST frames with REQ_KIND = refuse
    from hil.transport.codec import Codec

    codec = Codec()
    kinds = [codec.decode(fid, data).signals["REQ_KIND"]
             for _, fid, data in read_log(tmp_path / "bus.log") if fid == ID["DRIVER_REQUEST"]]
    assert fp.REQ_REFUSE in kinds
    # python-can's player accepts the log
    play = subprocess.run([sys.executable, "-m", "can.player", "-i", "virtual", "-c", "replay",
                           "--ignore-timestamps", str(tmp_path / "bus.log")],
                          capture_output=True, text=True, timeout=300)
    assert play.returncode == 0, play.stderr[-2000:]


def test_safety_override_scenario(tmp_path):
    """Comfort chosen; on the D stretch the tyre-deflection RMS passes the road-holding limit
    and the ECU enters safety mode by itself (reason road holding), then returns to comfort."""
    proc = hil_run(tmp_path, "--route", str(ROUTES / "override.toml"), "--mode", "comfort",
                   "--seed", "1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    rep = json.loads(proc.stdout)
    tr = np.load(tmp_path / "ecu.npz")
    mode = tr["mode"]
    safety = np.flatnonzero(mode == fp.MODE_SAFETY)
    assert len(safety) > 1000
    seg = np.load(tmp_path / "plant.npz")["segment"]
    assert set(np.unique(seg[safety]).tolist()) <= {1, 2}      # during or just after D
    assert mode[-1] == fp.MODE_COMFORT                           # and back
    assert "accept" not in rep["driver"]["requests"]             # nobody asked for it
    from hil.transport.codec import Codec

    codec = Codec()
    recs = [codec.decode(fid, data).signals for _, fid, data in read_log(tmp_path / "bus.log")
            if fid == ID["MODE_RECOMMEND"]]
    assert any(r["OVERRIDE"] == 1 and r["REASON"] == 1 and r["ACTIVE_MODE"] == fp.MODE_SAFETY
               for r in recs)
    # the override lowered the tyre deflection on the D stretch
    assert rep["segments"][1]["ratio"]["dtd"] < 1.0


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "zombie" not in Path(
        f"/proc/{pid}/status").read_text().lower()


def _default_sigint() -> None:
    """A suite started in the background by a non-interactive shell inherits SIGINT ignored,
    and Python then keeps it ignored; the supervisor must see Ctrl-C as a terminal sends it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_and_wait_for_nodes(out: Path, *extra):
    sup = subprocess.Popen([sys.executable, "-m", "hil", "run", "--out", str(out),
                            "--route", str(ROUTES / "override.toml"), "--mode", "comfort",
                            *extra],
                           cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           preexec_fn=_default_sigint)
    # a bench in User-mode Linux on a slow host takes minutes to start (CI saw over 120 s);
    # the run's own start-up timeouts end a bench that cannot start, this cap only a hang
    deadline = time.monotonic() + START_CAP_S
    while time.monotonic() < deadline and sup.poll() is None:
        kids = {pid: _cmdline(pid) for pid in _children(sup.pid)}
        if any(" plant " in c for c in kids.values()) and (out / "bus.log").exists() \
                and (out / "bus.log").stat().st_size > 100_000:
            return sup, kids
        time.sleep(0.2)
    sup.kill()
    _, err = sup.communicate()
    raise AssertionError(f"the bench did not start: {err[-2000:]}")


@pytest.mark.vcan        # (in make vcan-test: the same on vcan0)
def test_a_killed_node_stops_the_bench_with_a_clear_message(tmp_path):
    sup, kids = _start_and_wait_for_nodes(tmp_path)
    ecu = next(pid for pid, c in kids.items() if " ecu " in c)
    os.kill(ecu, signal.SIGKILL)
    _, err = sup.communicate(timeout=60)
    assert sup.returncode == 1
    assert "node ecu died" in err
    time.sleep(0.5)
    assert not [pid for pid in kids if _alive(pid)]      # no orphan: hub and nodes gone
    frames = read_log(tmp_path / "bus.log")               # readable up to the last frame
    assert len(frames) > 1000
    assert (tmp_path / "bus.log").read_bytes().endswith(b"\n")   # no torn last line
    assert any(f[1] == ID["ACTUATOR_CMD"] for f in frames[-50:])  # the ECU's frames to the end


@pytest.mark.vcan        # (in make vcan-test: the same on vcan0)
def test_ctrl_c_stops_everything_and_flushes_the_log(tmp_path):
    sup, kids = _start_and_wait_for_nodes(tmp_path)
    sup.send_signal(signal.SIGINT)
    _, err = sup.communicate(timeout=60)
    assert sup.returncode == 130
    assert "interrupted at t =" in err
    time.sleep(0.5)
    assert not [pid for pid in kids if _alive(pid)]
    text = (tmp_path / "bus.log").read_text()
    assert text.endswith("\n") and len(read_log(tmp_path / "bus.log")) > 1000


def _stalled_run(tmp_path, who: str, *extra):
    """Stop one process of a running bench (SIGSTOP, our own child by PID): the supervisor
    must stop the run in bounded time, name it, leave nothing running and a partial report."""
    sup, kids = _start_and_wait_for_nodes(tmp_path, "--stall-s", "3", "--json", *extra)
    pid = next(p for p, c in kids.items() if who in c)
    t0 = time.monotonic()
    os.kill(pid, signal.SIGSTOP)
    out, err = sup.communicate(timeout=60)
    took = time.monotonic() - t0
    time.sleep(0.5)
    assert not [p for p in kids if _alive(p)]            # no orphan, the stopped one included
    rep = json.loads(out)
    assert rep["verdict"] == "fail" and rep["incomplete"] in err
    assert json.loads((tmp_path / "report.json").read_text())["incomplete"] == rep["incomplete"]
    assert (tmp_path / "bus.log").read_bytes().endswith(b"\n")
    return sup.returncode, err, took


@pytest.mark.parametrize("who,name", [
    pytest.param(" plant ", "node plant", marks=pytest.mark.vcan),
    (" ecu ", "node ecu"), ("hil.hub", "the hub")])
def test_a_stopped_process_stops_the_run_and_is_named(tmp_path, who, name):
    code, err, took = _stalled_run(tmp_path, who)
    assert code == 1
    assert f"{name} made no progress for 3 s (the process is stopped)" in err
    assert took < 30                                      # 3 s, then a bounded shutdown


def test_a_stopped_plant_in_realtime_stops_the_run(tmp_path):
    code, err, _ = _stalled_run(tmp_path, " plant ", "--pace", "realtime")
    assert code == 1 and "node plant made no progress" in err
    # the ECU's fail-safe timer went quiet after a second of silence: 3 s of it are a few
    # thousand frames, not 3 x 1,200 per second
    frames = read_log(tmp_path / "bus.log")
    t_last_sensor = max(f[0] for f in frames if f[1] == ID["PLANT_SENSORS"])
    after = [f for f in frames if f[0] > t_last_sensor + 1.2]
    assert len(after) < 200, len(after)


@pytest.mark.parametrize("sig,code", [pytest.param(signal.SIGTERM, 143, marks=pytest.mark.vcan),
                                      (signal.SIGHUP, 129)])
def test_sigterm_and_sighup_stop_the_run_like_ctrl_c(tmp_path, sig, code):
    sup, kids = _start_and_wait_for_nodes(tmp_path)
    sup.send_signal(sig)
    _, err = sup.communicate(timeout=60)
    assert sup.returncode == code
    assert f"interrupted ({signal.Signals(sig).name}) at t =" in err
    time.sleep(0.5)
    assert not [pid for pid in kids if _alive(pid)]
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["verdict"] == "fail" and rep["incomplete"].startswith("interrupted")
    # the nodes wrote their records on SIGTERM: the partial report covers what was driven
    assert 0 < rep["duration_s"] < 30 and rep["segments"]
    assert (tmp_path / "bus.log").read_text().endswith("\n")


def test_a_second_run_on_the_same_out_refuses(tmp_path):
    # (a route that outlasts the two refusals: the override route can end in lockstep before
    # them on a fast bench, and then SIGINT found a finished run)
    sup, _ = _start_and_wait_for_nodes(tmp_path, "--route", "full_road_section")
    try:
        for cmd in (["run", "--duration", "1"], ["sim", "--duration", "1"]):
            proc = subprocess.run([sys.executable, "-m", "hil", *cmd, "--out", str(tmp_path)],
                                  capture_output=True, text=True, cwd=ROOT, timeout=120)
            assert proc.returncode == 2
            assert proc.stderr.count("\n") == 1 and "is in use by another run" in proc.stderr
    finally:
        sup.send_signal(signal.SIGINT)
        sup.communicate(timeout=60)
    assert sup.returncode == 130


@pytest.mark.vcan        # (in make vcan-test: the same on vcan0)
def test_a_node_without_a_bus_says_so(tmp_path):
    """A node started alone, on a channel this kernel does not have (auto selection: no such
    SocketCAN interface, and no hub given), says so; with a hub that is not there, too. (Not
    the default vcan0: a host that has it would connect, and wait for the plant.)"""
    env = {k: v for k, v in os.environ.items() if k not in ("CAN_INTERFACE", "CAN_CHANNEL")}
    key = ["--key-file", str(golden.key_file(tmp_path))]
    proc = subprocess.run([sys.executable, "-m", "hil", "ecu", "-c", "vcan9", *key],
                          capture_output=True, text=True, cwd=ROOT, timeout=120, env=env)
    assert proc.returncode == 3
    assert "no CAN bus: this kernel has no vcan9" in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "hil", "plant", "-i", "remote", "-c",
                           "ws://127.0.0.1:9/", *key], capture_output=True, text=True, cwd=ROOT,
                          timeout=120, env=env)
    assert proc.returncode == 3
    assert "cannot reach the bus" in proc.stderr


def test_bad_driver_script_is_a_one_line_error(tmp_path):
    bad = tmp_path / "s.toml"
    bad.write_text('[[request]]\nt_s = 1.0\nkind = "choose"\nmode = "sport"\n')
    proc = subprocess.run([sys.executable, "-m", "hil", "run", "--out", str(tmp_path / "o"),
                           "--driver", "script", "--script", str(bad)], capture_output=True,
                          text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "request[0].mode" in proc.stderr


def test_realtime_pacing_runs_and_reports_its_deadlines(tmp_path):
    """Realtime pacing: the plant holds 1 kHz; how many deadlines were missed is reported
    (the figure itself is a benchmark, not a test)."""
    # (this checks the mechanics on a test host running other tests in parallel; the timing
    # figures are make bench's, the default limits a user's. Only the timing checks may fail
    # here, as on vcan0 in UML: on a loaded host without SCHED_FIFO (CI) the ECU's own timer
    # fires before a late sensor frame, the missing sample faults every ADC channel for
    # recover_ticks (50) ticks, and the fail-safe share reached 0.59-0.80 of 3 s with four
    # busy loops beside it, at 0.18 missed deadlines. Every other check must hold, and the
    # exit code must say the verdict)
    proc = hil_run(tmp_path, "--route", str(ROUTES / "refusal.toml"), "--mode", "comfort",
                   "--pace", "realtime", "--duration", "3", "--max-missed-ratio", "0.3",
                   "--max-lost-ratio", "0.3")
    assert proc.returncode in (0, 1), proc.stderr[-2000:]
    rep = json.loads(proc.stdout)
    assert_only_timing_failed(proc.returncode, rep)
    by = {c["name"]: c for c in rep["checks"]}
    assert set(by) >= REALTIME_TIMING
    assert by["missed_deadline_ratio"]["limit"] == "<= 0.3"
    rt = rep["bench"]["realtime"]
    assert by["missed_deadline_ratio"]["value"] == rt["missed_deadline_ratio"]
    assert rep["bench"]["pace"] == "realtime" and rep["duration_s"] == pytest.approx(3.0)
    # the ratio is the misses over the 3000 ticks of the run (not over some other count)
    assert rt["missed_deadline_ratio"] == rt["missed_deadlines"] / 3000
    assert rt["lag_p50_us"] <= rt["lag_p99_us"] <= rt["lag_max_us"]
    # real-time scheduling asked for: granted (SCHED_FIFO 60, the plant's) or said refused
    assert rt["sched"] == "SCHED_FIFO 60" or rt["sched"].startswith("SCHED_OTHER (SCHED_FIFO")
    frames = read_log(tmp_path / "bus.log")
    assert len(frames) == rep["bench"]["frames_logged"]
    stamps = [f[0] for f in frames]
    assert stamps == sorted(stamps) and 2.5 < stamps[-1] - stamps[0] < 10.0   # wall clock
