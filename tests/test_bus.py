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


def test_hub_filters_per_client_and_copies_frames_independently():
    """Acceptance filters act in the hub (a node gets only what it reads); every receiver gets
    the same frames in the order sent, with their own metadata, from the shallow copies."""
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
            assert plant.recv(0.3) is None
        finally:
            for bus in (sender, everything, plant):
                bus.shutdown()


def test_hub_copies_are_shallow_but_independent():
    import copy

    from can.interfaces import virtual

    from hil.hub import fast_virtual_copies

    saved = virtual.deepcopy
    try:
        fast_virtual_copies()
        a = can.Bus(interface="virtual", channel="t_copy")
        b = can.Bus(interface="virtual", channel="t_copy")
        c = can.Bus(interface="virtual", channel="t_copy")
        msg = can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=False)
        a.send(msg)
        mb, mc = b.recv(1.0), c.recv(1.0)
        assert mb is not mc and mb is not msg and mb.equals(mc) and mb.equals(msg, timestamp_delta=None, check_channel=False)
        mb.timestamp = -1.0
        assert mc.timestamp != -1.0
        for bus in (a, b, c):
            bus.shutdown()
    finally:
        virtual.deepcopy = saved
    assert virtual.deepcopy is copy.deepcopy
