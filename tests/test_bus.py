"""Transport: bus selection and the remote hub on 127.0.0.1 (this machine has no kernel CAN)."""

import subprocess
import sys
from pathlib import Path

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.transport.bus import BusError, BusSpec, Hub, close_bus, kernel_has_vcan, resolve

pytestmark = pytest.mark.hil
ROOT = Path(__file__).resolve().parents[1]


def test_auto_selects_the_hub_without_kernel_can(monkeypatch):
    monkeypatch.delenv("CAN_INTERFACE", raising=False)
    monkeypatch.delenv("CAN_CHANNEL", raising=False)
    spec, needs_hub = resolve()
    if kernel_has_vcan():
        assert spec == BusSpec("socketcan", "vcan0") and not needs_hub
    else:
        assert spec is None and needs_hub


def test_environment_and_refusals(monkeypatch):
    monkeypatch.setenv("CAN_INTERFACE", "remote")
    monkeypatch.setenv("CAN_CHANNEL", "ws://127.0.0.1:5000/")
    assert resolve() == (BusSpec("remote", "ws://127.0.0.1:5000/"), False)
    with pytest.raises(BusError, match="127.0.0.1"):
        resolve("remote", "ws://10.0.0.5:5000/")
    with pytest.raises(BusError, match="leaves the machine"):
        resolve("udp_multicast", "239.0.0.1")
    monkeypatch.delenv("CAN_CHANNEL")
    with pytest.raises(BusError, match="needs a channel"):
        resolve("socketcan", None)


def test_hub_relays_frames_between_clients_and_stops_cleanly():
    with Hub() as hub:
        a = BusSpec("remote", hub.url).open()
        b = BusSpec("remote", hub.url).open()
        try:
            a.send(can.Message(arbitration_id=0x100, data=bytes(range(8)), is_extended_id=False))
            m = b.recv(2.0)
            assert m is not None and m.arbitration_id == 0x100 and bytes(m.data) == bytes(range(8))
        finally:
            a.shutdown()
            b.shutdown()
        pid = hub.proc.pid
    assert hub.proc.poll() is not None, f"hub {pid} still running"


def test_closing_the_bus_is_bounded_when_the_hub_is_stopped():
    """can_remote's shutdown waits for the hub's close handshake; with the hub stopped
    (SIGSTOP) ``close_bus`` gives up after its timeout and leaves no second attempt."""
    import os
    import signal
    import time

    with Hub() as hub:
        bus = BusSpec("remote", hub.url).open()
        os.kill(hub.proc.pid, signal.SIGSTOP)
        try:
            t0 = time.monotonic()
            assert close_bus(bus, timeout_s=1.0) is False
            assert time.monotonic() - t0 < 3.0
            assert bus._is_shutdown
        finally:
            os.kill(hub.proc.pid, signal.SIGCONT)
        bus = BusSpec("remote", hub.url).open()
        assert close_bus(bus) is True                    # a live hub: the normal handshake


def test_closing_a_bus_whose_hub_is_gone_prints_nothing_at_exit():
    """The hub gone first (a drive that ended): can_remote's shutdown raises (ENOTCONN);
    ``close_bus`` swallows it and marks the bus shut, so python-can's ``__del__`` does not try
    again and print a traceback after the tool's one line."""
    code = ("import time\n"
            "from hil.transport.bus import BusSpec, Hub, close_bus\n"
            "with Hub() as hub:\n"
            "    bus = BusSpec('remote', hub.url).open()\n"
            "time.sleep(0.3)\n"
            "assert close_bus(bus, timeout_s=2.0) and bus._is_shutdown\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, timeout=60)
    assert p.returncode == 0 and p.stderr == "", p.stderr


def test_unreachable_bus_says_so():
    with pytest.raises(BusError, match="cannot reach the bus"):
        BusSpec("remote", "ws://127.0.0.1:9/").open(timeout_s=0.5)


def test_hub_filters_per_client_and_keeps_the_order():
    """Acceptance filters act in the hub (a node gets only what it reads); every receiver gets
    the frames in the order sent; the sender never gets its own frames back."""
    from hil.bench.procs import node_filters

    with Hub() as hub:
        sender = BusSpec("remote", hub.url).open()
        everything = BusSpec("remote", hub.url).open()
        plant = BusSpec("remote", hub.url).open(can_filters=node_filters("plant"))
        try:
            sent = [(fid, bytes([i] * 8)) for i, fid in enumerate((0x100, 0x80, 0x200, 0x80))]
            for fid, data in sent:
                sender.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
            got_all = [everything.recv(2.0) for _ in sent]
            got_plant = [plant.recv(2.0) for _ in range(2)]
            assert [(m.arbitration_id, bytes(m.data)) for m in got_all] == sent
            assert [(m.arbitration_id, bytes(m.data)) for m in got_plant] == \
                [f for f in sent if f[0] == 0x80]
            assert all(not m.is_extended_id and m.dlc == 8 for m in got_all)
            assert plant.recv(0.3) is None and sender.recv(0.1) is None
        finally:
            for bus in (sender, everything, plant):
                bus.shutdown()


def _raw_client(port: int, protocol: str):
    """A bare python-can-remote WebSocket with the library's own framing (the methods
    hil.transport.bus.fast_remote_client replaced)."""
    from can_remote import protocol as rp
    from can_remote import websocket as ws

    from hil.transport.bus import fast_remote_client

    fast_remote_client()

    class Plain(ws.WebSocket):
        send_frame, read_frame, wait = ws.WebSocket._hil_original

    sock = Plain(f"ws://127.0.0.1:{port}/", [protocol])
    return rp.RemoteProtocolBase(sock), sock


def test_hub_speaks_the_json_protocol_and_answers_errors():
    """A can.json.v1 client (no binary frames) and a binary one see each other's frames; an
    unsupported request gets an error event, not a dropped connection."""
    import json

    with Hub() as hub:
        proto, sock = _raw_client(hub.port, "can.json.v1")
        assert sock.protocol == "can.json.v1"
        proto.send("bus_request", {"config": {}})
        assert json.loads(sock.read())["type"] == "bus_response"
        binary = BusSpec("remote", hub.url).open()
        try:
            proto.send("message", {"arbitration_id": 0x123, "is_extended_id": False,
                                   "dlc": 3, "data": [1, 2, 3]})
            m = binary.recv(2.0)
            assert m.arbitration_id == 0x123 and bytes(m.data) == b"\x01\x02\x03"
            binary.send(can.Message(arbitration_id=0x1ABCDE, data=b"\xff", is_extended_id=True))
            got = proto.recv(2.0)
            assert isinstance(got, can.Message) and got.arbitration_id == 0x1ABCDE
            assert got.is_extended_id and bytes(got.data) == b"\xff"
            proto.send("periodic_start", {"period": 0.1, "msg": {}})
            with pytest.raises(Exception, match="not supported"):
                proto.recv(2.0)
        finally:
            binary.shutdown()
            sock.close()


def test_fast_client_framing_is_the_protocol():
    """hil.transport.bus.fast_remote_client sends what the library's reader parses and reads what the
    library sends: frames between a patched and an unpatched client through the hub."""
    with Hub() as hub:
        proto, sock = _raw_client(hub.port, "can.binary+json.v1")
        proto.send("bus_request", {"config": {}})
        assert proto.recv(2.0)["type"] == "bus_response"
        fast = BusSpec("remote", hub.url).open()
        try:
            for n in (0, 1, 5, 8):
                fast.send(can.Message(arbitration_id=0x10 + n, data=bytes(range(n)),
                                      is_extended_id=False))
                m = proto.recv(2.0)
                assert (m.arbitration_id, bytes(m.data)) == (0x10 + n, bytes(range(n)))
                proto.send_msg(can.Message(arbitration_id=0x20 + n, data=bytes([7] * n),
                                           is_extended_id=False))
                m = fast.recv(2.0)
                assert (m.arbitration_id, bytes(m.data)) == (0x20 + n, bytes([7] * n))
        finally:
            fast.shutdown()
            sock.close()


def test_websocket_framing_round_trips_at_every_length_form():
    """hil.transport.wsframe, the hub's and the clients' one framing: a frame parses back to its opcode
    and payload, masked or not, at the 7-bit, 16-bit and 64-bit length forms' edges; the
    accept key is RFC 6455's example."""
    from hil.transport import wsframe

    for n in (0, 1, 125, 126, 0xFFFF, 0x10000):
        payload = bytes(i % 251 for i in range(n))
        for mask in (None, b"\x01\x80\xfe\x7f"):
            f = wsframe.frame(wsframe.BINARY, payload, mask)
            pos = wsframe.header_size(f[1])
            opcode, length, key = wsframe.header(f)
            assert (opcode, length, key) == (wsframe.BINARY, n, mask) and len(f) == pos + n
            body = f[pos:]
            assert (wsframe.xor(body, key) if key else body) == payload
            assert mask is None or n == 0 or body != payload
    assert wsframe.accept_key("dGhlIHNhbXBsZSBub25jZQ==") == "s3pPLMBiTxaQ9kYGzzhZRbK+xOo="


def test_hub_refuses_plain_http_and_survives_garbage():
    import socket

    with Hub() as hub:
        with socket.create_connection(("127.0.0.1", hub.port), timeout=2.0) as s:
            s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
            assert s.recv(100).startswith(b"HTTP/1.1 404")
        with socket.create_connection(("127.0.0.1", hub.port), timeout=2.0) as s:
            s.sendall(bytes(range(256)) * 100)          # not HTTP: dropped when too long
        a = BusSpec("remote", hub.url).open()
        b = BusSpec("remote", hub.url).open()
        try:
            a.send(can.Message(arbitration_id=0x7, data=b"ok", is_extended_id=False))
            assert bytes(b.recv(2.0).data) == b"ok"
        finally:
            a.shutdown()
            b.shutdown()


def test_hub_drops_a_client_that_stops_reading():
    """A client that never reads cannot stall the others: past its backlog limit it is
    dropped (here 64 KiB instead of the hub's 16 MiB, to keep the test short)."""
    import socket

    from hil.transport import hub as hubmod

    server = hubmod.HubServer(0, max_backlog=64 * 1024)
    import threading

    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    url = f"ws://127.0.0.1:{server.port}/"
    try:
        stuck, sock = _raw_client(server.port, "can.binary+json.v1")
        stuck.send("bus_request", {"config": {}})
        assert stuck.recv(2.0)["type"] == "bus_response"
        # small kernel buffers on both ends, so the backlog lands in the hub quickly
        sock.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        server.clients[0].sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        a = BusSpec("remote", url).open()
        b = BusSpec("remote", url).open()
        try:
            payload = bytes(8)
            n = server.max_backlog // 10 + 5000
            got = 0
            for i in range(n):
                a.send(can.Message(arbitration_id=0x100, data=payload, is_extended_id=False))
                while b.recv(0) is not None:
                    got += 1
            while b.recv(0.5) is not None:
                got += 1
            assert got == n                       # the reading client lost nothing
            assert server.dropped_clients == 1    # the stuck one was dropped
        finally:
            a.shutdown()
            b.shutdown()
            sock.socket.close()
    finally:
        server.running = False
        t.join(2.0)
        server.close()


def test_rt_priority_never_raises_and_says_what_it_got():
    from hil.transport.bus import RT_OFFSET, rt_of, set_rt_priority

    assert set_rt_priority(0) == "SCHED_OTHER"
    got = set_rt_priority(1000)                       # out of range: refused, not raised
    assert got.startswith("SCHED_OTHER (SCHED_FIFO refused")
    assert rt_of(0, "plant") == 0
    assert rt_of(50, "plant") > rt_of(50, "hub") > rt_of(50, "ecu") > rt_of(50, "app") > 0
    assert set(RT_OFFSET) == {"plant", "hub", "ecu", "app"}


# -- the hub against malformed clients --------------------------------------------------------

def _ws_message(opcode: int, payload: bytes) -> bytes:
    """A masked client-to-server WebSocket message (RFC 6455)."""
    import os
    import struct

    head = bytes([0x80 | opcode])
    n = len(payload)
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 1 << 16:
        head += bytes([0x80 | 126]) + struct.pack(">H", n)
    else:
        head += bytes([0x80 | 127]) + struct.pack(">Q", n)
    mask = os.urandom(4)
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


class _LiveHub:
    """A HubServer in a thread of this process, with two well-behaved python-can clients."""

    def __init__(self):
        import threading

        from hil.transport.bus import free_port
        from hil.transport.hub import HubServer

        self.log: list[str] = []
        self.server = HubServer(free_port(), log=self.log.append)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        url = f"ws://127.0.0.1:{self.server.port}/"
        self.a, self.b = BusSpec("remote", url).open(), BusSpec("remote", url).open()

    def raw(self, messages: list[bytes], bus_request: bool = True) -> bytes:
        """Connect, upgrade, (request the bus,) send ``messages``; what came back."""
        import base64
        import json
        import os
        import socket

        with socket.create_connection(("127.0.0.1", self.server.port), timeout=2.0) as s:
            key = base64.b64encode(os.urandom(16)).decode()
            s.sendall((f"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade"
                       f"\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Protocol: can.json.v1"
                       f"\r\n\r\n").encode())
            if bus_request:
                s.sendall(_ws_message(1, json.dumps({"type": "bus_request",
                                                     "payload": {"config": {}}}).encode()))
            for m in messages:
                try:
                    s.sendall(m)
                except OSError:          # the hub hung up on us: what it should do
                    break
            s.settimeout(0.3)
            got = b""
            try:
                while chunk := s.recv(65536):
                    got += chunk
            except OSError:
                pass
            return got

    def relays(self) -> bool:
        """The good clients still talk through the hub."""
        import can

        self.a.send(can.Message(arbitration_id=0x42, data=b"alive", is_extended_id=False))
        m = self.b.recv(2.0)
        return m is not None and bytes(m.data) == b"alive"

    def close(self):
        self.a.shutdown()
        self.b.shutdown()
        self.server.running = False
        self.thread.join(5.0)
        self.server.close()


@pytest.fixture
def live_hub():
    hub = _LiveHub()
    yield hub
    hub.close()


@pytest.mark.parametrize("payload, reason", [
    ({"arbitration_id": 0x80, "dlc": 300, "data": [1]}, "dlc 300"),
    ({"arbitration_id": -1, "dlc": 1, "data": [1]}, "arbitration_id -1"),
    ({"arbitration_id": 0x800, "is_extended_id": False, "data": []}, "11-bit"),
    ({"arbitration_id": 0x80, "data": 300000000}, "data must be a list"),
    ({"arbitration_id": 0x80, "data": [1, 2, 256]}, "0..255"),
    ({"arbitration_id": 0x80, "data": list(range(9))}, "9 data bytes"),
    ({"arbitration_id": 0x80, "dlc": 4, "data": [1]}, "dlc 4 but 1"),
    ({"arbitration_id": 0x80, "is_fd": "yes", "data": []}, "is_fd must be true or false"),
    ({"arbitration_id": "0x80", "data": []}, "arbitration_id '0x80'"),
    ({"data": []}, "needs an arbitration_id"),
    ([1, 2, 3], "payload must be an object"),
])
def test_a_malformed_json_frame_disconnects_its_client_and_nothing_else(live_hub, payload,
                                                                        reason):
    import json

    got = live_hub.raw([_ws_message(1, json.dumps({"type": "message",
                                                   "payload": payload}).encode())])
    assert b"disconnected" in got
    assert any(reason in line for line in live_hub.log), live_hub.log
    assert live_hub.server.rejected_clients == 1 and live_hub.relays()


def test_oversized_and_binary_garbage_disconnect_before_anything_is_buffered(live_hub):
    import struct

    huge_header = bytes([0x81, 0x80 | 127]) + struct.pack(">Q", 300_000_000) + b"\0" * 4
    live_hub.raw([huge_header + b"x" * 100])
    assert any("300000000-byte message" in line for line in live_hub.log)
    live_hub.raw([_ws_message(2, b"\x01\x02")])                      # short binary frame
    bad_dlc = b"\x01" + struct.pack(">dIBB", 0.0, 0x80, 200, 0) + b"\0" * 3
    live_hub.raw([_ws_message(2, bad_dlc)])
    live_hub.raw([_ws_message(1, b"[[[[[[[[" * 500)])                  # not an event
    assert live_hub.server.rejected_clients == 4
    assert any("dlc 200" in line for line in live_hub.log)
    assert live_hub.relays()


def test_the_rate_limit_drops_the_excess_and_says_so():
    import can

    import threading
    import time

    from hil.transport.bus import free_port
    from hil.transport.hub import HubServer

    log = []
    server = HubServer(free_port(), log=log.append, rate_limit_fps=50)
    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    url = f"ws://127.0.0.1:{server.port}/"
    a, b = BusSpec("remote", url).open(), BusSpec("remote", url).open()
    try:
        t0 = time.monotonic()
        for k in range(200):                     # far faster than 50 per second
            a.send(can.Message(arbitration_id=0x10, data=[k % 256], is_extended_id=False))
        sent_s = time.monotonic() - t0
        got = 0
        while b.recv(0.5) is not None:
            got += 1
        # one second's bucket, then what refilled while the frames came in
        assert 50 <= got <= 50 + 50 * sent_s + 2, (got, sent_s)
    finally:
        a.shutdown()
        b.shutdown()
        server.running = False
        t.join(5.0)
        server.close()
    assert any("frames over the rate limit" in line for line in log), log


@settings(max_examples=120, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.lists(st.one_of(
    st.binary(max_size=200),                                          # raw bytes
    st.builds(lambda b: _ws_message(1, b), st.binary(max_size=300)),  # text frames of junk
    st.builds(lambda b: _ws_message(2, b), st.binary(max_size=40)),   # binary frames of junk
    st.builds(lambda j: _ws_message(1, j.encode()), st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
            st.sampled_from(["type", "payload", "arbitration_id", "dlc", "data", "is_fd",
                             "config", "can_filters", "x"]), inner, max_size=4),
        max_leaves=12).map(__import__("json").dumps)),
), max_size=4), bus_request=st.booleans())
def test_random_bytes_and_json_never_stop_the_hub(live_hub, data, bus_request):
    """Hypothesis throws random bytes, WebSocket frames and JSON at a live hub: the hub never
    dies and the well-behaved clients always still talk."""
    live_hub.raw(data, bus_request)
    assert live_hub.thread.is_alive()
    assert live_hub.relays()
