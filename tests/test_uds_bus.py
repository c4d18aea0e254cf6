"""UDS over ISO-TP on the bench (issue 19): random ISO-TP frames and UDS requests into the ECU
node between its control ticks, and the udsoncan tester (python -m hil diag) against a running
bench over the hub."""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware.diag import dtc
from hil import nodes
from hil.apps import diag
from hil.config import default_vehicle
from hil.nodes import ID
from hil.nodes.sil import ecu_params
from hil.transport import secoc
from hil.transport.codec import Codec
from tests.procutil import bench_run

ROOT = Path(__file__).resolve().parents[1]
P = ecu_params(default_vehicle(), "comfort")
KEY = secoc.new_key()


def _ecu():
    return nodes.EcuNode(P, Codec(), key=KEY)


def _sensor_frames(n: int):
    tx = nodes.Tx(Codec())
    out = []
    for k in range(n):
        f = []
        if k % 10 == 0:
            f.append(tx.frame_phys("VEHICLE_SPEED", {"SPEED": 20.0}))
        f.append(tx.frame("PLANT_SENSORS", {
            "BODY_ACCEL_RAW": 2048 + (k * 7) % 13, "WHEEL_ACCEL_RAW": 2048 - (k * 5) % 11,
            "SUSP_DEFL_RAW": 2048 + (k * 3) % 7, "MOTOR_CURRENT_RAW": 2048 + k % 5}))
        out.append(f)
    return out


def _drive(node, ticks, between=None):
    """Feed ``ticks`` of sensor frames; ``between(k)`` gives diagnostic frames to deliver
    before tick k. Returns the frames the node sent, per tick, without the diagnostic ones."""
    sent = []
    for k, frames in enumerate(ticks):
        if between is not None:
            for data in between(k):
                for fid, _ in node.on_frame(ID["DIAG_REQUEST"], data):
                    assert fid == diag.RESPONSE_ID
        for fid, data in frames:
            node.on_frame(fid, data)
        out = []
        while node.ready():
            out += [f for f in node.tick() if f[0] != diag.RESPONSE_ID]
            node.record()
        sent.append(out)
    return sent


FRAME = st.binary(min_size=0, max_size=8)
SINGLE = st.binary(min_size=1, max_size=7).map(lambda p: bytes([len(p)]) + p)   # SF, any UDS


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.lists(st.one_of(FRAME, SINGLE), max_size=3), min_size=40, max_size=40))
def test_random_isotp_frames_never_disturb_the_control_ticks(per_tick):
    """Random frames on DIAG_REQUEST (garbage ISO-TP and random single-frame UDS requests)
    between the ticks: no exception, answers only on DIAG_RESPONSE in 8-byte frames, and every
    control frame and the trace exactly as without them."""
    ticks = _sensor_frames(len(per_tick))
    a, b = _ecu(), _ecu()
    plain = _drive(a, ticks)
    busy = _drive(b, ticks, lambda k: per_tick[k])
    assert plain == busy
    assert a.summary()["trace_sha256"] == b.summary()["trace_sha256"] or b.resets
    # and a well-formed request still gets its answer afterwards
    resp = b.on_frame(ID["DIAG_REQUEST"], bytes([0x02, 0x3E, 0x00]).ljust(8, b"\xcc"))
    assert resp == [] or resp[-1][1][:3] == bytes([0x02, 0x7E, 0x00])


def test_a_multi_frame_response_follows_the_testers_flow_control():
    node = _ecu()
    _drive(node, _sensor_frames(5))
    # ReadDTCInformation 0x0A (every DTC: 3 + 4 x 24 bytes): first frame, then after the
    # tester's flow control every consecutive frame
    first = node.on_frame(ID["DIAG_REQUEST"], bytes([0x02, 0x19, 0x0A]).ljust(8, b"\xcc"))
    assert len(first) == 1 and first[0][1][0] >> 4 == 1          # FF
    size = (first[0][1][0] & 0xF) << 8 | first[0][1][1]
    assert size == 3 + 4 * len(dtc.DTCS)
    rest = node.on_frame(ID["DIAG_REQUEST"], bytes([0x30, 0, 0]).ljust(8, b"\xcc"))
    assert len(rest) == -(-(size - 6) // 7) and all(f[1][0] >> 4 == 2 for f in rest)
    assert all(len(f[1]) == 8 for f in first + rest)
    assert node.summary()["frames_sent"]["DIAG_RESPONSE"] == 1 + len(rest)


def test_an_ecu_reset_keeps_the_dtc_memory_and_starts_a_new_cycle():
    node = _ecu()
    _drive(node, _sensor_frames(5))
    node.state.diag.dtc.entries[dtc.BY_NAME["frame_counter"]].status |= dtc.CDTC
    sf = lambda *b: bytes([len(b), *b]).ljust(8, b"\xcc")      # noqa: E731
    assert node.on_frame(ID["DIAG_REQUEST"], sf(0x11, 0x01))[0][1][:3] == b"\x03\x7f\x11"
    node.on_frame(ID["DIAG_REQUEST"], sf(0x10, 0x03))
    assert node.on_frame(ID["DIAG_REQUEST"], sf(0x11, 0x01))[0][1][:3] == b"\x02\x51\x01"
    assert node.resets == 1 and node.state.diag.dtc.cycle == 1
    e = node.state.diag.dtc.entries[dtc.BY_NAME["frame_counter"]]
    assert e.status & dtc.CDTC and e.status & dtc.TNCTOC
    assert node.state.diag.session == 0x01          # a reset ends the extended session
    _drive(node, _sensor_frames(5))                 # and the ECU runs on


# -- the tester against a running bench ---------------------------------------------------------

def _diag(url, secret, *extra):
    return subprocess.run([sys.executable, "-m", "hil", "diag", "-i", "remote", "-c", url,
                           "--secret-file", str(secret), "--json", *extra],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)


@pytest.mark.hil
@pytest.mark.xdist_group("hub_bench")       # (two benches at once overload 2 cores)
def test_the_udsoncan_tester_reads_a_running_bench(tmp_path):
    out = tmp_path / "run"
    # the drive is lockstep (faster than real time): 40 s of it leave the tester's calls,
    # each a Python start, room on a loaded host; the clear follows the first ticking read
    with bench_run(ROOT, out, "--route", "full_road_section", "--mode", "comfort",
                   "--seed", "2", "--duration", "40") as (run, url):
        secret = out / "hub.secret"
        assert secret.stat().st_mode & 0o777 == 0o600
        # without the secret the tester is read-only: its request never reaches the ECU
        p = subprocess.run([sys.executable, "-m", "hil", "diag", "-i", "remote", "-c", url,
                            "--timeout", "1"], capture_output=True, text=True, cwd=ROOT,
                           timeout=60)
        assert p.returncode == 2 and "--secret-file" in p.stderr
        while run.poll() is None and not (out / "plant.log").exists():
            time.sleep(0.2)
        # read until the ECU ticks (the plant may still be warming up)
        doc = None
        for _ in range(60):
            p = _diag(url, secret)
            assert p.returncode == 0, p.stderr
            doc = json.loads(p.stdout)
            if doc["ecu"]["tick"] > 2000:
                break
            time.sleep(0.5)
        p = _diag(url, secret, "--clear")
        assert p.returncode == 0, (f"tick {doc['ecu']['tick']} at the last read, the run "
                                   f"{'still going' if run.poll() is None else 'ended'}: "
                                   f"{p.stderr[-1500:]}")
        assert json.loads(p.stdout)["cleared"]
        ecu = doc["ecu"]
        assert ecu["software_version"] == P.software_version
        assert ecu["calibration_sha256"] == P.calibration_sha256.hex()
        assert ecu["active_mode"] == "comfort" and ecu["fault_word"] == 0
        assert doc["dtcs"] == []                         # a fault-free drive
        stdout, stderr = run.communicate(timeout=600)
    assert run.returncode == 0, stderr[-2000:]
    rep = json.loads(stdout)
    assert rep["verdict"] == "pass"
    # the tester changed nothing in the drive: the trace of the same case without it
    sim = subprocess.run([sys.executable, "-m", "hil", "sim", "--route", "full_road_section",
                          "--mode", "comfort", "--seed", "2", "--duration", "40", "--json"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert json.loads(sim.stdout)["trace_sha256"] == rep["trace_sha256"]
    ecu_summary = json.loads((out / "ecu.json").read_text())
    assert ecu_summary["uds_requests"] >= 4 and ecu_summary["isotp_errors"] == 0


def test_the_tester_without_a_bench_says_so_in_one_line(tmp_path):
    secret = tmp_path / "s"
    secret.write_text("00" * 16)
    secret.chmod(0o600)                  # (a key file: hil.transport.secoc.load_key refuses others)
    p = _diag("ws://127.0.0.1:9/", secret)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1   # (docs: exit 1)
    assert "Traceback" not in p.stderr


def test_the_protocol_libraries_print_nothing_beside_the_testers_line():
    """can-isotp's and udsoncan's warnings reached stderr through logging's last resort (two
    isotp lines beside 'no answer' when the tester started before the ECU answered): the
    tester silences their loggers, its own line says what failed."""
    code = ("import logging\n"
            "from hil.apps.diag import PROTOCOL_LOGGERS, quiet_protocol_logs\n"
            "logging.getLogger('isotp').warning('before')\n"
            "quiet_protocol_logs()\n"
            "for n in PROTOCOL_LOGGERS:\n"
            "    logging.getLogger(n).warning('after')\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=60)
    assert p.returncode == 0 and p.stderr.strip().splitlines() == ["before"], p.stderr
