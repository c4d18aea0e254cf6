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
