"""Real SocketCAN: the bench on vcan0 in a real kernel, watched by can-utils' candump.

The tests marked ``needs_vcan`` need a kernel with CAN and vcan0 up: ``make vcan-test`` runs
them (with the other ``vcan``-marked tests) in User-mode Linux, where they are the only check
of the socketcan path; on a host without vcan0 they are deselected (tests/conftest.py says so
in one line). The launcher itself (``hil/transport/vcan.py``) is tested from the host
(tests/test_vcan_launcher.py). Lockstep runs, but one: UML has one CPU and a 100 Hz tick, so
realtime pacing runs and reports its figures there, with no verdict on deadlines.
"""

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import can
import pytest

from hil.transport import vcan_guest
from hil.transport.bus import SocketcanTap
from hil.transport.buslog import SIL_CHANNEL, compare, same_channel
from tests import golden
from tests.procutil import REALTIME_TIMING, assert_only_timing_failed

ROOT = Path(__file__).resolve().parents[1]
ROUTES = Path(__file__).resolve().parent / "routes"
SHORT = ("--route", "city", "--duration", "6")        # most tests: 6 simulated seconds
pytestmark = [pytest.mark.vcan, pytest.mark.needs_vcan, pytest.mark.hil]


def hil(*args, timeout=1500) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout)


def run_json(proc: subprocess.CompletedProcess) -> dict:
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def sent_total(report: dict) -> int:
    return sum(n for node in report["frames_sent"].values() for n in node.values())


@pytest.mark.slow
def test_full_road_section_on_vcan0_is_the_hub_run_and_candump_agrees(tmp_path):
    """The acceptance run on the real kernel path, once over the whole road section: auto
    selection picks vcan0; the trace and the log are the golden SIL's (which the hub run
    equals, tests/test_hil.py); candump, beside the bench, recorded the same frames in the
    same order; the logger lost nothing and the kernel reports no drop."""
    rec = vcan_guest.start_candump(tmp_path / "candump.log")
    try:
        proc = hil("run", "--route", "full_road_section", "--mode", "auto", "--seed", "1",
                   "--pace", "lockstep", "--out", str(tmp_path / "run"), "--json",
                   "--key-file", str(golden.key_file(tmp_path)), "--start-time",
                   golden.START_TIME)
    finally:
        assert vcan_guest.stop_candump(rec)
    rep = run_json(proc)
    assert "bus: socketcan vcan0" in proc.stderr             # auto chose the kernel's bus
    assert rep["bench"]["bus"] == "socketcan"
    gold = golden.load()["full_road_section_auto"]
    assert rep["trace_sha256"] == gold["trace_sha256"]
    log = tmp_path / "run" / "bus.log"
    assert log.read_text().startswith("(1767225600.000000) vcan0 ")
    assert hashlib.sha256(same_channel(log.read_bytes(), SIL_CHANNEL)).hexdigest() == \
        gold["buslog_sha256"]
    sent = sent_total(rep)
    assert rep["bench"]["frames_logged"] == sent and rep["bench"]["logger_kernel_drops"] == 0
    c = compare(tmp_path / "candump.log", log)
    assert c["equal"], c["first_difference"]
    assert c["frames"] == [sent, sent]
    # cantools decodes candump's own log
    dec = subprocess.run([sys.executable, "-m", "cantools", "decode",
                          str(ROOT / "dbc" / "suspension.dbc")],
                         stdin=open(tmp_path / "candump.log"), capture_output=True, text=True,
                         timeout=600)
    assert dec.returncode == 0 and "Unknown frame id" not in dec.stdout
    assert dec.stdout.count("ACTUATOR_CMD(") == rep["frames_sent"]["ECU"]["ACTUATOR_CMD"]


def test_vcan0_and_sil_give_the_same_trace_and_log(tmp_path):
    """A short case on vcan0 named explicitly (-i socketcan -c vcan0) and in one process (hil
    sim): one trace hash, and the same log bytes but for the channel. (The hub gives the SIL's
    trace and log too: tests/test_hil.py, on the host.)"""
    key = ("--key-file", str(golden.key_file(tmp_path)))
    common = (*SHORT, "--mode", "auto", "--seed", "3", *key, "--start-time",
              "2026-12-02T09:00:00Z", "--json")
    kern = run_json(hil("run", "-i", "socketcan", "-c", "vcan0", "--out",
                        str(tmp_path / "vcan"), *common))
    sim = run_json(hil("sim", "--out", str(tmp_path / "sim"), *common))
    assert kern["bench"]["bus"] == "socketcan"
    assert kern["trace_sha256"] == sim["trace_sha256"]
    sim_log = (tmp_path / "sim" / "bus.log").read_bytes()
    assert f") {SIL_CHANNEL} ".encode() in sim_log and b") vcan0 " not in sim_log
    assert same_channel(sim_log, "vcan0") == (tmp_path / "vcan" / "bus.log").read_bytes()


def test_the_fault_campaign_on_vcan0_gives_the_golden_hub_table(tmp_path):
    """Every fault that does not need a hub gives on vcan0 the row the hub gives
    (tests/golden/faults.json, which make test's campaign over the hub equals); the outside
    sender's forged commands, which the hub drops, reach the plant on vcan0 and its SecOC
    check rejects them all, with the same (lack of) effect."""
    out = tmp_path / "vcan"
    proc = hil("faults", "-i", "socketcan", "-c", "vcan0", "--out", str(out), "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    kern = {r["fault"]: r for r in golden.fault_rows(json.loads(proc.stdout)["results"], out)}
    hub = {r["fault"]: r for r in golden.load_faults()["results"]}
    assert set(kern) <= set(hub) and len(kern) >= len(hub) - 1
    assert set(hub) - set(kern) <= {"hub_message"}           # (no hub to attack on vcan0)
    for name, row in kern.items():
        if name == "external_sender":
            assert "dropped at the hub" in hub[name]["note"]
            assert row["note"] == "50 of 50 rejected by the plant's SecOC check"
            row, hub[name] = dict(row, note=None), dict(hub[name], note=None)
        assert golden.diff(hub[name], row) == [], name


def test_the_logger_counts_what_the_kernel_drops():
    """A logger that falls behind loses frames in the kernel: its drop counter counts them, so
    received + dropped is every frame sent (here a tap with the smallest buffer, not read
    while 3,000 frames are sent)."""
    tap = SocketcanTap("vcan0", rcvbuf=1)          # (the kernel rounds it up to its minimum)
    try:
        with can.Bus(interface="socketcan", channel="vcan0") as bus:
            for k in range(3000):
                bus.send(can.Message(arbitration_id=0x7F0, data=k.to_bytes(2, "big"),
                                     is_extended_id=False))
        got = []
        while (msg := tap.recv(0.2)) is not None:
            got.append(int.from_bytes(msg.data, "big"))
        assert tap.dropped > 0
        assert len(got) + tap.dropped == 3000
        assert got == sorted(got)                              # what arrived, in order
    finally:
        tap.shutdown()


def test_realtime_on_vcan0_runs_and_reports_its_figures(tmp_path):
    """Realtime pacing over the kernel's bus: it runs to the end and reports its deadline
    figures, and the logger still has every frame. No verdict on timing here: UML has one CPU
    for the three nodes and a 100 Hz tick (a sleep lasts at least 10 ms), so most 1 ms
    deadlines are missed and the ECU falls behind the plant (measured: 89 % missed, the ECU's
    trace 1.7 of 3 s, commands late so the plant falls back and the ECU's timer runs
    fail-safe ticks); the only checks allowed to fail are those timing ones. The timing goals
    are make bench's, on a host."""
    proc = hil("run", "-i", "socketcan", "-c", "vcan0", "--route", str(ROUTES / "refusal.toml"),
               "--mode", "comfort", "--pace", "realtime", "--duration", "3", "--out",
               str(tmp_path), "--json")
    assert proc.returncode in (0, 1), proc.stderr[-3000:]
    rep = json.loads(proc.stdout)
    assert "incomplete" not in rep, (rep["incomplete"], proc.stderr[-3000:])
    assert_only_timing_failed(proc.returncode, rep, REALTIME_TIMING | {"span_s"})
    rt = rep["bench"]["realtime"]
    assert rep["bench"]["bus"] == "socketcan" and rep["bench"]["pace"] == "realtime"
    assert rt["missed_deadline_ratio"] == rt["missed_deadlines"] / 3000
    assert rt["lag_p50_us"] <= rt["lag_p99_us"] <= rt["lag_max_us"]
    assert rep["bench"]["frames_logged"] == sent_total(rep)
    assert rep["bench"]["logger_kernel_drops"] == 0
