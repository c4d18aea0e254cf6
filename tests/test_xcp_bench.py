"""pyxcp as the master of a running bench (``python -m hil run``, lockstep, three processes),
over the hub and on vcan0 (``make vcan-test``: User-mode Linux): the acceptance of XCP on
CAN end to end. In one run of grade C in safety mode (120 s over the hub, 70 s on vcan0):

- the test's own pyxcp master, two seconds into the drive: a write while locked, one outside
  the A2L limits, one the safety design forbids and a DAQ over the bus budget are refused
  with their XCP errors; the safety LQR's row halved is accepted, and recorded with its tick;
- ``python -m hil xcp`` (the tool, on pyxcp): a DAQ within the budget on the 1 ms event, and
  (over the hub) one of the estimates on the 10 ms event, each for 20 s of the ECU's time,
  lose no DTO and equal the run's own trace at their ticks; a ``set`` outside the limits is
  refused;
- the run's verdict holds; its traces are, bit for bit, those of the same drive in one process
  with the same write at the same tick; and the change in the ride that the write made (against
  that drive unwritten: the same road) is what the exact analysis of the new gain predicts,
  within 3 sigma of the paired difference's scatter.

The virtual-bus tests (tests/test_xcp.py) cover each command and refusal on its own."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hil.apps import xcptool as xt
from hil.sim.road import load_route
from hil.xcp import protocol as px
from tests import golden
from tests.procutil import bench_run
from tests.test_xcp import RES, Collect, P, _list
from tests.test_xcp_tuning import drive, log_ratios, predicted_change

pyxcp = pytest.importorskip("pyxcp")
from pyxcp.types import XcpResponseError, XcpTimeoutError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ROUTE = Path(__file__).resolve().parent / "routes" / "xcp_tuning.toml"
GRADE, SPEED = "C", 20.0               # (the route's one segment)
WRITE_AFTER = 2000                     # the write: once the drive has reached this tick
FROM = 15_000                          # the ride is compared from this tick to the end
SETTLE = 1000                          # ticks the write has to settle before FROM
GAIN = "cal.control.k_safety"

# (bus, seconds of the route driven, the 10 ms DAQ too): on vcan0 in UML (one CPU, about
# 0.45x real time in lockstep) the 1 ms DAQ only, over 70 s: the hub run covers the rest
BUSES = [pytest.param("hub", 120, True, marks=[pytest.mark.hil,
                                               pytest.mark.xdist_group("hub_bench")]),
         pytest.param("vcan0", 70, False, marks=[pytest.mark.hil, pytest.mark.vcan,
                                                 pytest.mark.needs_vcan])]


def _bus(kind: str, url) -> tuple[str, str]:
    """The bus as -i/-c name it."""
    return ("remote", url) if kind == "hub" else ("socketcan", "vcan0")


def _bus_args(kind: str, url, out: Path) -> list[str]:
    """The tool's bus arguments (on the hub, with the run's secret: the DBC's TESTER)."""
    interface, channel = _bus(kind, url)
    secret = ["--secret-file", str(out / "hub.secret")] if kind == "hub" else []
    return ["-i", interface, "-c", channel, *secret]


def _connect(x, seconds: float = 300.0):
    """CONNECT, again until the ECU node is up and answers."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            return x.connect()
        except XcpTimeoutError:
            if time.monotonic() > deadline:
                raise


def _refused(code: int, f, *args) -> None:
    with pytest.raises(XcpResponseError) as e:
        f(*args)
    assert int(e.value.get_error_code()) == code, px.ERROR_NAMES.get(
        int(e.value.get_error_code()))


def _tune(bus, key: bytes, a2l) -> tuple[np.ndarray, np.ndarray]:
    """Once the drive is WRITE_AFTER ticks in: the refused writes and DAQ, then the safety
    row halved: (the gain before, the one written)."""
    it, tick = a2l.item(GAIN), a2l.item("in.tick")
    over = Collect([_list(0, 1, ("out.faults", "out.force_cmd_n", "out.road_est_um"))])
    with xt.connected(bus, key, policy=over, timeout=2.0) as x:
        _connect(x)
        deadline = time.monotonic() + 600
        while xt.read(x, tick)[0] < WRITE_AFTER:          # (a write during the drive)
            assert time.monotonic() < deadline, "the drive did not reach the write's tick"
            time.sleep(0.05)
        k0 = np.asarray(xt.read(x, it))
        half = (0.5 * k0).tobytes()
        _refused(px.ERR_ACCESS_LOCKED, xt.push, x, it.address, half)     # locked
        xt.session(x, a2l)                                   # EPK checked, unlocked
        _refused(px.ERR_OUT_OF_RANGE, xt.push, x, it.address,
                 (5.0 * k0).tobytes())                        # outside the A2L limits
        assert it.lower <= (1.5 * k0).min() and (1.5 * k0).max() <= it.upper
        _refused(px.ERR_OUT_OF_RANGE, xt.push, x, it.address,
                 (1.5 * k0).tobytes())                        # inside them, but unstable
        np.testing.assert_array_equal(xt.read(x, it), k0)
        over.setup()
        _refused(px.ERR_DAQ_CONFIG, over.start)           # every tick, 3 outputs: over budget
        xt.push(x, it.address, half)
        np.testing.assert_array_equal(xt.read(x, it), 0.5 * k0)
        x.disconnect()
    return k0, 0.5 * k0


def _xcp(bus_args, key_file: Path, *argv):
    return subprocess.run([sys.executable, "-m", "hil", "xcp", *argv, *bus_args,
                           "--key-file", str(key_file), "--json"],
                          capture_output=True, text=True, cwd=ROOT, timeout=900)


@pytest.mark.slow
@pytest.mark.parametrize("kind, seconds, slow_daq", BUSES)
def test_pyxcp_tunes_and_measures_a_running_bench(kind, seconds, slow_daq, tmp_path):
    from asammdf import MDF

    from hil.apps.diag import open_tester_bus

    out = tmp_path / "run"
    bus_extra = [] if kind == "hub" else _bus_args(kind, None, out)   # (the hub: it makes it)
    a2l = xt.A2l()
    key_file = golden.key_file(tmp_path)
    with bench_run(ROOT, out, "--route", str(ROUTE), "--mode", "safety", "--seed", "1",
                   "--pace", "lockstep", "--key-file", str(key_file),
                   "--start-time", golden.START_TIME, "--duration", str(seconds),
                   *bus_extra) as (run, url):
        bus = open_tester_bus(*_bus(kind, url), out / "hub.secret" if kind == "hub" else None,
                              response_id=RES)
        try:
            k0, k1 = _tune(bus, golden.secoc_key(), a2l)
        finally:
            bus.shutdown()
        args = _bus_args(kind, url, out)
        fast = _xcp(args, key_file, "measure", "out.force_cmd_n", "out.enable", "--event",
                    "1ms", "--prescaler", "8", "--seconds", "20", "--out",
                    str(tmp_path / "f.mf4"))
        slow = slow_daq and _xcp(args, key_file, "measure", "out.force_cmd_n",
                                 "out.road_est_um", "out.active_mode", "--event", "10ms",
                                 "--seconds", "20", "--out", str(tmp_path / "s.mf4"))
        bad = _xcp(args, key_file, "set", f"{GAIN}[2]", "1e9")
        stdout, stderr = run.communicate(timeout=1800)
    # the bench's checks hold; the ride (hil.validate.ride) judges the law the write left,
    # half the safety gain, against safety's acceptance: the exit code carries its verdict
    rep = json.loads(stdout)
    assert run.returncode == (0 if rep["verdict"] == "pass" else 1), stderr[-2000:]
    bench = [c for c in rep["checks"] if not c["name"].startswith("ride.")]
    assert bench and all(c["ok"] for c in bench), [c for c in bench if not c["ok"]]
    assert [c["name"] for c in rep["checks"] if c["name"].startswith("ride.")] == \
        ["ride.segment1.safety"]
    assert bad.returncode == 1 and "ERR_OUT_OF_RANGE" in bad.stderr, bad.stderr

    # the DAQs: every sample, equal to the run's own trace at its tick
    trace = dict(np.load(out / "ecu.npz"))
    daqs = [(fast, 8, {"out.force_cmd_n": trace["force_cmd"],
                       "out.enable": trace["enable"].astype(float)})]
    if slow_daq:
        daqs.append((slow, 10, {"out.force_cmd_n": trace["force_cmd"],
                                "out.road_est_um": trace["road_est"],
                                "out.active_mode": trace["mode"].astype(float)}))
    for p, step, checks in daqs:
        assert p.returncode == 0, p.stderr
        doc = json.loads(p.stdout)
        assert doc["lost"] == 0 and doc["samples"] == 20_000 // step
        with MDF(doc["out"]) as mdf:
            for name, want in checks.items():
                sig = mdf.get(name)
                ticks = np.round(sig.timestamps * 1000).astype(int)
                assert np.all(np.diff(ticks) == step)
                np.testing.assert_array_equal(sig.samples, want[ticks], err_msg=name)

    # the write: one, whole, recorded with its tick, early enough to have settled by FROM
    xcp = json.loads((out / "ecu.json").read_text())["xcp"]
    (cal,) = xcp["calibrations"]
    w = cal["tick"]
    assert WRITE_AFTER <= w <= FROM - SETTLE, f"the write came at tick {w}"
    assert xcp["refusals"] == {"ERR_ACCESS_LOCKED": 1, "ERR_OUT_OF_RANGE": 3,
                               "ERR_DAQ_CONFIG": 1}, xcp["refusals"]

    # the same drive in one process, with the same write at the same tick: the same traces
    route = load_route(str(ROUTE))
    plant = dict(np.load(out / "plant.npz"))
    assert len(plant["ba"]) == seconds * 1000
    t1, e1 = drive(route, writes=(w, GAIN, k1), ticks=seconds * 1000)
    for name in t1:
        np.testing.assert_array_equal(plant[name], t1[name], err_msg=f"plant {name}")
    for name in e1:
        np.testing.assert_array_equal(trace[name], e1[name], err_msg=f"ecu {name}")

    # the ride changed as the exact analysis of the new gain predicts
    t0, _ = drive(route, ticks=seconds * 1000)
    measured = log_ratios(plant, FROM) - log_ratios(t0, FROM)
    predicted, sigma = predicted_change(k0, k1, GRADE, SPEED,
                                        (len(plant["ba"]) - FROM) * P.dt_s)
    assert np.all(np.abs(measured - predicted) < 3 * sigma), (measured, predicted, sigma)
    assert np.max(np.abs(measured) / sigma) > 10, (measured, sigma)
