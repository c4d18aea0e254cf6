"""The bus log in the formats engineers open (issue 20): candump -L dated from the run's start,
with its channel and direction; ASC, BLF and TRC through python-can's writers and MF4 through
asammdf, each read back frame for frame; can-utils' log2asc on the candump log; cantools
decode naming modes, grades, reasons and faults."""

import datetime as dt
import json
import shutil
import subprocess
import sys
from pathlib import Path

import can
import pytest

from hil.nodes import ID
from hil.transport.buslog import (LOG_FORMATS, SIL_CHANNEL, convert, dut_tx_ids, parse_formats,
                        parse_start_time, read_log)
from hil.transport.codec import DBC_PATH, Codec

ROOT = Path(__file__).resolve().parents[1]
START = "2026-12-02T09:00:00Z"
START_S = dt.datetime(2026, 12, 2, 9, tzinfo=dt.timezone.utc).timestamp()
pytestmark = pytest.mark.slow


def hil(*args, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A short SIL run that writes every format (--log-format given both ways)."""
    out = tmp_path_factory.mktemp("sim")
    proc = hil("sim", "--route", "city", "--duration", "3", "--mode", "comfort", "--out",
               str(out), "--start-time", START, "--log-format", "asc,blf",
               "--log-format", "trc,mf4", "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out, json.loads(proc.stdout)


def frames(msgs) -> list[tuple[int, bytes, bool]]:
    return [(m.arbitration_id, bytes(m.data), m.is_rx) for m in msgs]


def test_candump_log_is_dated_from_the_start_with_channel_and_direction(run):
    out, rep = run
    assert rep["bench"]["logs"] == ["bus.log", "bus.asc", "bus.blf", "bus.trc", "bus.mf4"]
    lines = (out / "bus.log").read_text().splitlines()
    assert len(lines) == rep["bench"]["frames_logged"] > 3000
    assert lines[0].startswith(f"({START_S:.6f}) {SIL_CHANNEL} ")
    stamps = [float(line[1:line.index(")")]) for line in lines]
    assert stamps == sorted(stamps) and START_S <= stamps[-1] < START_S + 3.01
    tx = dut_tx_ids()
    assert tx == {ID[n] for n in ("ACTUATOR_CMD", "ECU_STATUS", "ECU_ESTIMATES",
                                  "MODE_RECOMMEND", "DIAG_RESPONSE", "XCP_RES")}
    for line in lines:                # T: the ECU (the device under test) sent it; R: others
        fid = int(line.split()[2].split("#")[0], 16)
        assert line.endswith(" T" if fid in tx else " R"), line


@pytest.mark.parametrize("fmt", [f for f in LOG_FORMATS if f != "log"])
def test_every_format_reads_back_with_the_same_frames_times_and_direction(run, fmt):
    out, _ = run
    ref = list(can.LogReader(str(out / "bus.log")))
    kwargs = {"relative_timestamp": False} if fmt == "asc" else {}
    got = list(can.LogReader(str(out / f"bus.{fmt}"), **kwargs))
    assert frames(got) == frames(ref)
    # times: the run's own, dated (ASC to the millisecond of its header date, then exact)
    tol = 1.5e-3 if fmt == "asc" else 1.5e-6
    assert all(abs(g.timestamp - r.timestamp) <= tol for g, r in zip(got, ref))
    assert abs(got[0].timestamp - START_S) <= tol


def test_asc_and_blf_carry_the_runs_date(run):
    out, _ = run
    head = (out / "bus.asc").read_text().splitlines()[:4]
    assert head[0] == "date Wed Dec 02 09:00:00.0 2026"
    assert head[3] == "Begin Triggerblock Wed Dec 02 09:00:00.0 2026"
    with can.BLFReader(str(out / "bus.blf")) as blf:
        assert blf.start_timestamp == pytest.approx(START_S, abs=1e-3)


def test_mf4_decodes_with_the_dbc_in_asammdf(run):
    from asammdf import MDF

    out, _ = run
    codec = Codec()
    status = [codec.decode(fid, data, scaling=False).signals
              for _, fid, data in read_log(out / "bus.log") if fid == ID["ECU_STATUS"]]
    with MDF(str(out / "bus.mf4")) as mdf:
        assert mdf.header.start_time == dt.datetime.fromtimestamp(START_S, dt.timezone.utc)
        decoded = mdf.extract_bus_logging({"CAN": [(str(DBC_PATH), 0)]})
        mode = decoded.get("CAN0.ECU_STATUS.ACTIVE_MODE", raw=True)
    assert len(status) > 100
    assert mode.samples.tolist() == [s["ACTIVE_MODE"] for s in status]
    assert mode.timestamps[0] >= 0 and mode.timestamps[-1] < 3.01


def test_can_utils_log2asc_reads_the_candump_log(run, tmp_path):
    if shutil.which("log2asc") is None:
        pytest.skip("Debian's can-utils (log2asc) is not installed (as root: apt-get install "
                    "can-utils; .ci/run installs it)")
    out, rep = run
    asc = tmp_path / "l2a.asc"
    subprocess.run(["log2asc", "-I", str(out / "bus.log"), "-O", str(asc), SIL_CHANNEL],
                   check=True, timeout=120)
    lines = asc.read_text().splitlines()
    assert sum(line.startswith("date ") for line in lines) == 1     # one header
    assert lines[0] == "date Wed Dec  2 09:00:00 2026"
    body = [line.split() for line in lines[3:]]
    assert len(body) == rep["bench"]["frames_logged"]
    times = [float(b[0]) for b in body]
    assert times == sorted(times) and times[0] == 0.0                # monotonic from the start
    assert {b[3] for b in body} == {"Rx", "Tx"}


def test_cantools_decode_names_modes_grades_reasons_and_faults(run):
    out, _ = run
    with open(out / "bus.log") as log:
        dec = subprocess.run([sys.executable, "-m", "cantools", "decode", str(DBC_PATH)],
                             stdin=log, capture_output=True, text=True, timeout=300)
    assert dec.returncode == 0
    text = dec.stdout
    assert "ACTIVE_MODE: comfort" in text and "RECOMMENDED_MODE: " in text
    assert "REASON: none" in text and "FAULT_PLAUSIBILITY: ok" in text
    assert any(f"ESTIMATED_GRADE: {g}" in text for g in ("A", "B", "C", "D", "unknown"))


def test_conversion_is_deterministic(run, tmp_path):
    out, _ = run
    copy = tmp_path / "bus.log"
    shutil.copy(out / "bus.log", copy)
    paths = convert(copy, LOG_FORMATS, parse_start_time(START))
    assert [p.name for p in paths] == ["bus.asc", "bus.blf", "bus.trc", "bus.mf4"]
    for p in paths:
        assert p.read_bytes() == (out / p.name).read_bytes(), p.name


def test_bad_log_options_are_one_line_errors(tmp_path):
    for args, what in ((("--start-time", "yesterday"), "--start-time"),
                       (("--start-time", "1e12"), "outside"),
                       (("--log-format", "pcap"), "--log-format")):
        proc = hil("sim", "--duration", "1", "--out", str(tmp_path / "o"), *args)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
        assert what in proc.stderr
    assert parse_formats(["MF4, asc", "log"]) == ("log", "mf4", "asc")
    assert parse_start_time("1796202000") == parse_start_time(START) == START_S * 1e6
