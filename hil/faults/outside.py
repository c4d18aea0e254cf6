"""Faults from outside the nodes: a bus client that sends forged commands, and one that sends
the hub a malformed message. The campaign's outside client performs them (``act``), counting
the plant's ticks from the bus."""

from __future__ import annotations

import json
from dataclasses import dataclass

from hil.faults.base import Evidence, Fault, Result
from hil.faults.commands import Attack, forged_command
from hil.nodes import ID


@dataclass(frozen=True, kw_only=True)
class ExternalSender(Attack):
    """A client without credentials sends a forged ACTUATOR_CMD with every tick: the hub drops
    it (read-only client) or, on vcan0, the plant's SecOC check rejects it."""
    node: str = "bus"

    def act(self, bus, spec, k: int, codec, on_bus: dict) -> bool:
        """Tick ``k`` of the attack on ``bus`` (opened from ``spec``, hil.transport.bus's
        BusSpec); False: done. ``on_bus`` counts the frames it put on the bus itself (vcan0:
        no hub drops them)."""
        import can

        bus.send(can.Message(arbitration_id=ID["ACTUATOR_CMD"], is_extended_id=False,
                             data=forged_command(codec, k & 0xF, k & 0x3, k)))
        if spec.interface != "remote":
            on_bus["ACTUATOR_CMD"] = on_bus.get("ACTUATOR_CMD", 0) + 1
        return True

    def rejected_from(self, seg: slice) -> slice:
        return slice(seg.start, None)     # (a rejected frame may be booked a tick later)


@dataclass(frozen=True, kw_only=True)
class HubMessage(Fault):
    """A client opens a WebSocket to the hub and sends a frame with DLC 300: detected when the
    hub disconnected it, recovered when the run went on."""
    node: str = "bus"
    safety: bool = False
    needs_hub: bool = True

    def act(self, bus, spec, k: int, codec, on_bus: dict) -> bool:
        malformed_hub_message(spec.channel)
        return False

    def judge(self, ev: Evidence) -> Result:
        hit = "disconnecting" in ev.hub_log and "dlc 300" in ev.hub_log
        return Result(self.name, hit, 0 if hit else None, hit and not ev.crashed, ev.crashed,
                      False, note="the hub disconnected the client" if hit else "not in hub.log")

    def table_note(self, r: Result) -> str:
        return r.note


def malformed_hub_message(url: str) -> None:
    """A client that opens a WebSocket to the hub and sends a frame with DLC 300."""
    import socket
    from urllib.parse import urlparse

    from hil.transport import wsframe

    u = urlparse(url)
    with socket.create_connection((u.hostname, u.port), timeout=2.0) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: "
                     b"Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                     b"Sec-WebSocket-Protocol: can.json.v1\r\n\r\n")
        for event in ({"type": "bus_request", "payload": {"config": {}}},
                      {"type": "message", "payload": {"arbitration_id": ID["ACTUATOR_CMD"],
                                                      "dlc": 300, "data": [1]}}):
            sock.sendall(wsframe.frame(wsframe.TEXT, json.dumps(event).encode()))
        try:
            while sock.recv(4096):
                pass
        except OSError:
            pass
