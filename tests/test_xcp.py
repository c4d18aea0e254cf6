"""The ECU node's XCP slave (hil.xcp) under pyxcp as the master, in one process: python-can's
virtual bus between them, the node ticking on its own timer between commands (no plant: the
ECU runs fail-safe; what is checked is the protocol, the memory and the calibration)."""

from __future__ import annotations

import logging
import struct
import threading
import time

import can
import numpy as np
import pytest

from calib.image import Image
from calib.options import load_options
from hil.apps.xcptool import push
from hil.config import default_vehicle
from hil.nodes import EcuNode
from hil.nodes.sil import ecu_params
from hil.transport.codec import Codec
from hil.xcp import protocol as px
from hil.xcp.port import xcp_secret
from hil.xcp.slave import key_of

pyxcp = pytest.importorskip("pyxcp")
from pyxcp.config import create_application_from_config  # noqa: E402
from pyxcp.daq_stim import DaqList, DaqOnlinePolicy  # noqa: E402
from pyxcp.master import Master  # noqa: E402
from pyxcp.types import XcpResponseError  # noqa: E402

CODEC = Codec()
KEY = bytes(range(16))
CMD, RES = CODEC.message("XCP_CMD").frame_id, CODEC.message("XCP_RES").frame_id
P = ecu_params(default_vehicle(), "auto")
IMAGE = Image(P)


class Bench:
    """An ECU node served on a virtual bus: its XCP answers, a timer tick when idle."""

    def __init__(self, channel: str):
        self.node = EcuNode(P, CODEC, key=KEY)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _send(self, frames) -> None:
        for fid, data in frames:
            if fid == RES:
                self.bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))

    def _serve(self) -> None:
        while not self.stop.is_set():
            m = self.bus.recv(0.0005)
            if m is not None and m.arbitration_id == CMD:
                self._send(self.node.on_frame(CMD, bytes(m.data)))
            elif m is None:
                self.node.timer_tick()
                self._send(self.node.tick())

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.bus.shutdown()


def master(channel: str, key: bytes = KEY, policy=None) -> Master:
    secret = xcp_secret(key)
    app = create_application_from_config(
        {"Transport": {"CAN": {"can_id_master": CMD, "can_id_slave": RES,
                               "max_dlc_required": True}},
         "General": {"disable_error_handling": True,
                     "seed_n_key_function": lambda res, seed: key_of(secret, bytes(seed))}},
        log_level=logging.WARNING)
    app.transport.layer = "CAN"
    return Master("can", config=app, transport_layer_interface=can.Bus(
        interface="virtual", channel=channel), policy=policy)


@pytest.fixture
def bench(request):
    b = Bench(request.node.name)
    yield b
    b.close()


def _code(exc) -> int:
    return int(exc.value.get_error_code())


def unlocked(x) -> None:
    """CONNECT, the communication modes (master block mode), GET_SEED/UNLOCK of both."""
    x.connect()
    x.getCommModeInfo()
    x.cond_unlock()


def _read(x, name: str) -> np.ndarray:
    o = IMAGE.objects[name]
    x.setMta(o.address)
    return np.frombuffer(x.upload(o.size)[:o.size], o.dtype)


def test_connect_epk_and_locked_resources(bench, request):
    with master(request.node.name) as x:
        r = x.connect()
        assert (r.maxCto, r.maxDto) == (8, 8) and r.resource.calpag and r.resource.daq
        st = x.getStatus().resourceProtectionStatus
        assert st.calpag and st.daq                       # locked until unlocked
        x.setMta(IMAGE.segment("IDENT").base)               # the master's EPK check
        assert x.upload(len(IMAGE.epk))[:len(IMAGE.epk)].decode() == IMAGE.epk
        assert x.identifier(1) == px.A2L_NAME
        o = IMAGE.objects["cal.control.k_safety"]
        x.setMta(o.address)
        with pytest.raises(XcpResponseError) as e:        # a write while locked
            x.download(np.zeros(5).tobytes()[:6])
        assert _code(e) == px.ERR_ACCESS_LOCKED
        with pytest.raises(XcpResponseError) as e:        # in master block mode: one ERR
            push(x, o.address, np.zeros(5).tobytes())     # for the block, not one per frame
        assert _code(e) == px.ERR_ACCESS_LOCKED
        assert x.getStatus().resourceProtectionStatus.calpag    # (its own answer)
        with pytest.raises(XcpResponseError) as e:
            x.freeDaq()
        assert _code(e) == px.ERR_ACCESS_LOCKED
        x.cond_unlock()
        st = x.getStatus().resourceProtectionStatus
        assert not st.calpag and not st.daq
        x.disconnect()


def test_a_wrong_key_is_refused_and_ends_the_session(bench, request):
    with master(request.node.name, key=bytes(16)) as x:
        x.connect()
        with pytest.raises(XcpResponseError) as e:
            x.cond_unlock()
        assert _code(e) == px.ERR_ACCESS_LOCKED
    assert not bench.node.xcp.slave.connected
    assert bench.node.xcp.summary()["refusals"] == {"ERR_ACCESS_LOCKED": 1}


def test_a_gain_write_is_applied_whole_between_ticks_in_both_paths(bench, request):
    o = IMAGE.objects["cal.control.k_safety"]
    with master(request.node.name) as x:
        unlocked(x)
        k = _read(x, o.name)
        np.testing.assert_array_equal(k, P.control.k_safety)
        new = k * 0.8                                  # (1.25x: unstable, refused)
        push(x, o.address, new.tobytes())               # (DOWNLOAD + DOWNLOAD_NEXT: a block)
        np.testing.assert_array_equal(_read(x, o.name), new)
        deadline = time.monotonic() + 5
        while not bench.node.xcp.log and time.monotonic() < deadline:
            time.sleep(0.01)
        entry = bench.node.xcp.log[-1]
        assert entry["objects"][o.name] == (k.tolist(), new.tolist())
        st = bench.node.state
        np.testing.assert_array_equal(st.P[0]["control"]["k_safety"], new)
        # the fixed-point tables follow (FX segment, read back over XCP)
        got = []
        for i in range(5):
            f = IMAGE.objects[f"fx.k_safety[{i}]"]
            got.append(float(_read(x, f.name)[0]) * 2.0 ** -f.frac)
        np.testing.assert_allclose(got, new, rtol=1e-6)
        # the reference page still holds the design
        x.setCalPage(px.PAGE_XCP, 0, 0)
        np.testing.assert_array_equal(_read(x, o.name), k)
        x.disconnect()


def test_the_working_page_saved_as_a_design_file_reads_back(bench, request, tmp_path):
    """python -m hil xcp save (its verb, over the virtual bus): the object written, and only
    it, goes to the design file's [calibration] table; --design reads back the same values."""
    import argparse

    from calib.calpage import WRITABLE
    from hil.apps.xcpcli import _save
    from hil.apps.xcptool import A2l

    tuned = np.asarray(P.control.k_safety) * 0.9
    with master(request.node.name) as x:
        unlocked(x)
        push(x, IMAGE.objects["cal.control.k_safety"].address, tuned.tobytes())
        x.disconnect()
    f = tmp_path / "tuned.toml"
    args = argparse.Namespace(file=str(f), design=None, timeout=2.0)
    bus = can.Bus(interface="virtual", channel=request.node.name)
    try:
        doc = _save(args, KEY, A2l(), bus, [])
    finally:
        bus.shutdown()
    assert doc["changed"] == ["control.k_safety"] and doc["objects"] == len(WRITABLE)
    back = ecu_params(default_vehicle(), "auto", opts=load_options(f))
    np.testing.assert_array_equal(back.control.k_safety, tuned)
    assert back.control.regen_c == P.control.regen_c


def test_refused_writes_leave_the_calibration_alone(bench, request):
    o = IMAGE.objects["cal.control.k_safety"]
    with master(request.node.name) as x:
        unlocked(x)
        k = _read(x, o.name)
        lo, hi = o.lower, o.upper
        assert lo <= (k * 1.5).min() and (k * 1.5).max() <= hi   # (inside the A2L limits,
        for value, code in ((k * 5.0, px.ERR_OUT_OF_RANGE),    # but its closed loop is not
                            (k * 1.5, px.ERR_OUT_OF_RANGE),    # stable: refused)
                            (np.where(np.arange(5) == 2, np.nan, k), px.ERR_OUT_OF_RANGE)):
            with pytest.raises(XcpResponseError) as e:
                push(x, o.address, value.tobytes())
            assert _code(e) == code
        ro = IMAGE.objects["cal.akf.phi"]
        with pytest.raises(XcpResponseError) as e:
            push(x, ro.address, np.zeros(1).tobytes())
        assert _code(e) == px.ERR_WRITE_PROTECTED
        with pytest.raises(XcpResponseError) as e:       # (measurement memory)
            push(x, IMAGE.objects["out.force_cmd_n"].address, bytes(4))
        assert _code(e) == px.ERR_WRITE_PROTECTED
        x.setCalPage(px.PAGE_XCP, 0, 0)                   # the reference page
        with pytest.raises(XcpResponseError) as e:
            push(x, o.address, k.tobytes())
        assert _code(e) == px.ERR_WRITE_PROTECTED
        x.setCalPage(px.PAGE_XCP, 0, 1)
        np.testing.assert_array_equal(_read(x, o.name), k)
        x.disconnect()
    assert bench.node.xcp.log == []
    np.testing.assert_array_equal(bench.node.state.P[0]["control"]["k_safety"], k)


class Collect(DaqOnlinePolicy):
    def __init__(self, lists):
        # (a logger given: pyxcp then reads no command line and no config file)
        super().__init__(lists, logger=logging.getLogger("test_xcp"))
        self.pid_off = False
        self.rows = []

    def initialize(self):
        pass

    def finalize(self):
        pass

    def on_daq_list(self, n, t0, t1, payload):
        self.rows.append((n, t1, list(payload)))


def _list(event: int, prescaler: int, names) -> DaqList:
    kinds = {"i4": "I32", "u1": "U8"}
    time.sleep(0.05)                                     # (the node has ticked)
    ms = [(n, IMAGE.objects[n].address, 0, kinds[IMAGE.objects[n].dtype]) for n in names]
    return DaqList(name="l", event_num=event, stim=False, enable_timestamps=True,
                   measurements=ms, priority=0, prescaler=prescaler)


def test_daq_samples_every_tenth_tick_and_loses_none(bench, request):
    names = ("in.tick", "out.faults", "out.active_mode", "out.enable")
    pol = Collect([_list(1, 1, names)])
    with master(request.node.name, policy=pol) as x:
        unlocked(x)
        pol.setup()
        pol.start()
        time.sleep(0.5)
        pol.stop()
        x.disconnect()
    rows = pol.rows
    assert len(rows) > 10
    heads = [h[0] for h in pol.daq_lists[0].headers]
    got_rows = [dict(zip(heads, payload)) for _, _, payload in rows]
    ticks = [g["in.tick"] for g in got_rows]
    assert all(t % 10 == 0 for t in ticks) and ticks[0] > 0
    assert ticks == list(range(ticks[0], ticks[-1] + 1, 10))          # no sample lost
    # (pyxcp hands the DTO timestamps over relative to the first: 1 ms per tick)
    assert [t1 for _, t1, _ in rows] == [(t - ticks[0]) * 1_000_000 for t in ticks]
    trace = bench.node.trace()
    for got, tick in zip(got_rows, ticks):
        assert got["out.faults"] == trace["faults"][tick]
        assert got["out.active_mode"] == trace["mode"][tick]
        assert got["out.enable"] == trace["enable"][tick]


def test_a_daq_over_the_bus_budget_is_refused(bench, request):
    names = ("out.faults", "out.force_cmd_n", "out.road_est_um")
    pol = Collect([_list(0, 1, names)])                  # 1 ms: ~27 % more per ODT
    with master(request.node.name, policy=pol) as x:
        unlocked(x)
        pol.setup()                                       # (selects the list)
        with pytest.raises(XcpResponseError) as e:       # START_STOP_SYNCH: refused
            pol.start()
        assert _code(e) == px.ERR_DAQ_CONFIG
        x.disconnect()
    assert not bench.node.xcp.daq.running


def test_malformed_ctos_get_errors_not_crashes():
    node = EcuNode(P, CODEC, key=KEY)
    assert node.on_frame(CMD, b"\xf5\x08") == []         # not connected: no answer
    (fid, res), = node.on_frame(CMD, b"\xff\x00")
    assert fid == RES and res[0] == px.RES and len(res) == 8
    for cto, code in ((b"\xf6", px.ERR_CMD_SYNTAX), (b"\x01", px.ERR_CMD_UNKNOWN),
                      (b"\xfc", px.ERR_CMD_SYNCH),
                      (b"\xf6\x00\x00\x00" + struct.pack("<I", 0x12345678), None)):
        out = node.on_frame(CMD, cto)
        if code is not None:
            assert out[0][1][:2] == bytes([px.ERR, code]), cto
    (_, res), = node.on_frame(CMD, b"\xf5\x04")          # UPLOAD outside the image
    assert res[:2] == bytes([px.ERR, px.ERR_ACCESS_DENIED])


def test_the_a2l_promises_only_commands_the_slave_answers():
    from calib.a2l import OPTIONAL_CMDS
    from hil.xcp.slave import _HANDLERS

    assert {getattr(px, name) for name in OPTIONAL_CMDS} <= set(_HANDLERS)
    assert len(OPTIONAL_CMDS) == len(set(OPTIONAL_CMDS))


# (python -m hil xcp and pyxcp against a running bench, over the hub and on vcan0:
# tests/test_xcp_bench.py)

def _cto(node, data: bytes) -> bytes:
    """One CTO into the node between ticks; its (single) answer."""
    (fid, res), = node.on_frame(CMD, data)
    assert fid == RES
    return res


def _write_between_ticks(node, name: str, values) -> None:
    """CONNECT, unlock calibration, DOWNLOAD (master block mode) ``values`` into ``name``."""
    o = IMAGE.objects[name]
    _cto(node, b"\xff\x00")
    seed = _cto(node, bytes([px.GET_SEED, 0, px.RES_CAL_PAG]))[2:8]
    assert _cto(node, bytes([px.UNLOCK, 6]) + key_of(xcp_secret(KEY), seed))[0] == px.RES
    _cto(node, bytes([px.SET_MTA, 0, 0, 0]) + struct.pack("<I", o.address))
    data = np.asarray(values, dtype=o.dtype).tobytes()
    assert node.on_frame(CMD, bytes([px.DOWNLOAD, len(data)]) + data[:6]) == []
    rest = data[6:]
    while rest:
        part, rest = rest[:6], rest[6:]
        out = node.on_frame(CMD, bytes([px.DOWNLOAD_NEXT, len(part) + len(rest)]) + part)
    assert out[0][1][0] == px.RES, out
    _cto(node, bytes([px.DISCONNECT]))


def _lockstep(writes: dict):
    """A lockstep run in this process (the nodes frame by frame), 3 s of the full road section
    in auto mode; ``writes``: tick -> (name, values), each written between that tick and
    the one before. Returns the ECU's trace hash and its calibration log."""
    from hil.nodes import PlantNode, run_in_process
    from hil.nodes.sil import app_node

    from hil.sim.road import load_route

    cfg = default_vehicle()
    route = load_route("full_road_section")
    p = ecu_params(cfg, "auto")
    plant = PlantNode(cfg, route, 1, CODEC, key=KEY)
    plant.n = 3000
    ecu = EcuNode(p, CODEC, lockstep=True, key=KEY)
    app = app_node(CODEC, "auto", p.dt_s, "auto", None, key=KEY)
    for tick in sorted(writes):
        run_in_process(plant, ecu, app, until=tick)
        _write_between_ticks(ecu, *writes[tick])
    run_in_process(plant, ecu, app)
    return ecu.summary()["trace_sha256"], ecu.xcp.log if ecu.xcp else []


def test_the_same_writes_at_the_same_ticks_give_the_same_bytes():
    """Lockstep: a calibration written between the same two ticks twice gives the same trace;
    written a tick later, or not at all, another (so the check can fail). (The energy mode's
    damping: the ECU runs energy feedback from tick 2500 of this drive.)"""
    k = [P.control.regen_c * 1.5]
    a, log_a = _lockstep({2600: ("cal.control.regen_c", k)})
    b, log_b = _lockstep({2600: ("cal.control.regen_c", k)})
    c, _ = _lockstep({2601: ("cal.control.regen_c", k)})
    d, _ = _lockstep({})
    assert a == b and len({a, c, d}) == 3
    assert log_a == log_b and [e["tick"] for e in log_a] == [2600]
