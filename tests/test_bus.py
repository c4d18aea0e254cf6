"""Transport: bus selection and the remote hub on 127.0.0.1 (this machine has no kernel CAN)."""

import can
import pytest

from hil.bus import BusError, BusSpec, Hub, kernel_has_vcan, resolve

pytestmark = pytest.mark.hil


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


def test_unreachable_bus_says_so():
    with pytest.raises(BusError, match="cannot reach the bus"):
        BusSpec("remote", "ws://127.0.0.1:9/").open(timeout_s=0.5)


def test_hub_filters_per_client_and_keeps_the_order():
    """Acceptance filters act in the hub (a node gets only what it reads); every receiver gets
    the frames in the order sent; the sender never gets its own frames back."""
    from hil.procs import node_filters

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
    hil.bus.fast_remote_client replaced)."""
    from can_remote import protocol as rp
    from can_remote import websocket as ws

    from hil.bus import fast_remote_client

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
    """hil.bus.fast_remote_client sends what the library's reader parses and reads what the
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

    from hil import hub as hubmod

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
    from hil.bus import RT_OFFSET, rt_of, set_rt_priority

    assert set_rt_priority(0) == "SCHED_OTHER"
    got = set_rt_priority(1000)                       # out of range: refused, not raised
    assert got.startswith("SCHED_OTHER (SCHED_FIFO refused")
    assert rt_of(0, "plant") == 0
    assert rt_of(50, "plant") > rt_of(50, "hub") > rt_of(50, "ecu") > rt_of(50, "app") > 0
    assert set(RT_OFFSET) == {"plant", "hub", "ecu", "app"}
