"""Opening the bus: ``socketcan`` on ``vcan0`` where the kernel has CAN, else python-can's
``remote`` hub (the ``can_remote`` server on a ``virtual`` bus) on 127.0.0.1.

Interface and channel come from python-can's usual arguments (``-i/-c``, ``CAN_INTERFACE``,
``CAN_CHANNEL``); ``auto`` (the default) chooses as above. Every socket stays on this machine:
a remote hub is bound to 127.0.0.1 and clients may only connect to a loopback URL, and the
``udp_multicast`` interface (which leaves the machine) is refused.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional
from urllib.parse import urlparse

import can

LOOPBACK = "127.0.0.1"
FORBIDDEN_INTERFACES = ("udp_multicast",)


class BusError(RuntimeError):
    """The bus cannot be reached or the bus options are not allowed. One-line message."""


def kernel_has_vcan(channel: str = "vcan0") -> bool:
    """True when the kernel supports AF_CAN and ``channel`` exists and is up."""
    try:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except (AttributeError, OSError):
        return False
    s.close()
    state = Path(f"/sys/class/net/{channel}/operstate")
    try:
        return state.read_text().strip() in ("up", "unknown")
    except OSError:
        return False


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def check_remote_url(url: str) -> str:
    parsed = urlparse(url)
    if parsed.scheme not in ("ws", "wss") or parsed.hostname not in (LOOPBACK, "localhost"):
        raise BusError(f"remote bus URL must be ws://127.0.0.1:PORT/, got {url!r}")
    return url


@dataclass
class BusSpec:
    interface: str
    channel: str

    def open(self, timeout_s: float = 5.0,
             can_filters: Optional[list[dict]] = None) -> can.BusABC:
        """Open the bus, retrying until ``timeout_s`` (a hub may still be starting).
        ``can_filters`` (python-can's acceptance filters) are applied where the frames are
        fanned out: in the kernel (socketcan) or in the hub (remote), so frames a node does not
        read never reach its process."""
        if self.interface in FORBIDDEN_INTERFACES:
            raise BusError(f"interface {self.interface!r} leaves the machine; not allowed")
        if self.interface == "remote":
            check_remote_url(self.channel)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                bus = can.Bus(interface=self.interface, channel=self.channel,
                              can_filters=can_filters)
                if self.interface == "remote":
                    _no_delay(bus)
                return bus
            except Exception as exc:  # noqa: BLE001 - every backend raises its own errors
                if time.monotonic() >= deadline:
                    raise BusError(f"cannot reach the bus {self.interface}:{self.channel}: "
                                   f"{type(exc).__name__}: {exc}") from None
                time.sleep(0.05)


def die_with_parent() -> None:
    """Child side of a fork (Linux): get SIGTERM when the parent dies, so a bench process
    never outlives the supervisor that started it."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _no_delay(bus: can.BusABC) -> None:
    """Small frames must leave at once: without TCP_NODELAY the client's second frame of a
    tick waits for the ACK of the first (Nagle + delayed ACK, up to 40 ms)."""
    sock = getattr(bus, "socket", None)
    if sock is not None:
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            pass


class Hub:
    """python-can's remote server on a ``virtual`` bus (``hil.hub``: can_remote with cheaper
    frame copies), bound to 127.0.0.1, as a child process that only its owner stops (by
    PID)."""

    def __init__(self, port: Optional[int] = None):
        self.port = port or free_port()
        self.proc: Optional[subprocess.Popen] = None

    @property
    def url(self) -> str:
        return f"ws://{LOOPBACK}:{self.port}/"

    def start(self, timeout_s: float = 10.0) -> "Hub":
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil.hub", "-p", str(self.port)],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True, preexec_fn=die_with_parent)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise BusError(f"the CAN hub exited at start (code {self.proc.returncode})")
            try:
                with socket.create_connection((LOOPBACK, self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.05)
        self.stop()
        raise BusError(f"the CAN hub did not open port {self.port} within {timeout_s:g} s")

    def stop(self, timeout_s: float = 5.0) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout_s)

    def __enter__(self) -> "Hub":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def resolve(interface: Optional[str] = None, channel: Optional[str] = None
            ) -> tuple[Optional[BusSpec], bool]:
    """Choose the bus. Returns (spec, needs_hub): with ``needs_hub`` the caller starts a
    :class:`Hub` and uses ``BusSpec('remote', hub.url)``."""
    interface = interface or os.environ.get("CAN_INTERFACE") or "auto"
    channel = channel or os.environ.get("CAN_CHANNEL")
    if interface in FORBIDDEN_INTERFACES:
        raise BusError(f"interface {interface!r} leaves the machine; not allowed")
    if interface == "auto":
        if kernel_has_vcan(channel or "vcan0"):
            return BusSpec("socketcan", channel or "vcan0"), False
        return None, True
    if interface == "remote":
        if not channel:
            return None, True
        return BusSpec("remote", check_remote_url(channel)), False
    if not channel:
        raise BusError(f"interface {interface!r} needs a channel (-c or CAN_CHANNEL)")
    return BusSpec(interface, channel), False
