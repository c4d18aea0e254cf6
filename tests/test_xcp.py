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
        new = k * 1.25
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


def test_refused_writes_leave_the_calibration_alone(bench, request):
    o = IMAGE.objects["cal.control.k_safety"]
    with master(request.node.name) as x:
        unlocked(x)
        k = _read(x, o.name)
        for value, code in ((k * 5.0, px.ERR_OUT_OF_RANGE),
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
    ms = [(n, IMAGE.objects[n].address, 0, kinds[IMAGE.objects[n].dtype]) for n in names]
    return DaqList(name="l", event_num=event, stim=False, enable_timestamps=True,
                   measurements=ms, priority=0, prescaler=prescaler)


def test_daq_samples_every_tenth_tick_and_loses_none(bench, request):
    names = ("out.faults", "out.active_mode", "out.enable")
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
    ticks = [t1 // 1_000_000 for _, t1, _ in rows]        # (the ECU's time: tick x 1 ms)
    assert all(t % 10 == 0 for t in ticks)
    assert ticks == list(range(ticks[0], ticks[-1] + 1, 10))          # no sample lost
    trace = bench.node.trace()
    heads = [h[0] for h in pol.daq_lists[0].headers]
    for (_, t1, payload), tick in zip(rows, ticks):
        got = dict(zip(heads, payload))
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
