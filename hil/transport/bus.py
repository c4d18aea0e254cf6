"""Opening the bus: ``socketcan`` on ``vcan0`` where the kernel has CAN, else python-can's
``remote`` interface to the bench's hub (``hil.hub``, which speaks can_remote's protocol) on
127.0.0.1.

Interface and channel come from python-can's usual arguments (``-i/-c``, ``CAN_INTERFACE``,
``CAN_CHANNEL``); ``auto`` (the default) chooses as above. Every socket stays on this machine:
a remote hub is bound to 127.0.0.1 and clients may only connect to a loopback URL, and the
``udp_multicast`` interface (which leaves the machine) is refused.
"""

from __future__ import annotations

import os
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional
from urllib.parse import urlparse

import can

from hil.transport import wsframe
from hil.transport.auth import SECRET_ENV, credentials

LOOPBACK = "127.0.0.1"
FORBIDDEN_INTERFACES = ("udp_multicast",)
RT_PRIORITY = 50            # SCHED_FIFO base priority of the bench's processes (realtime)
# above the base: the plant is the clock (it must wake at its deadline even when another
# bench process runs on that core), the hub relays, the ECU answers; the app may wait
RT_OFFSET = {"plant": 10, "hub": 5, "ecu": 0, "app": -5}


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


SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
SO_MEMINFO = 55                 # u32[SK_MEMINFO_VARS]; index 8: SK_MEMINFO_DROPS
SK_MEMINFO_DROPS = 8
TAP_RCVBUF = 32 << 20       # the logger's socket buffer on socketcan (~100k frames queued)
_CAN_FRAME = struct.Struct("=IB3x8s")       # struct can_frame (classic CAN, 16 bytes)


class SocketcanTap:
    """The bench's own receive-only socket on a SocketCAN channel (the logger's): a raw
    CAN socket with a large receive buffer (``SO_RCVBUFFORCE`` where allowed, else
    ``SO_RCVBUF`` up to the system's ``net.core.rmem_max``) and the kernel's drop counter,
    so a frame the kernel had to drop because the logger fell behind is counted
    (``dropped``), never silently missing. The counter is the socket's ``sk_drops``, read
    with ``SO_MEMINFO`` when asked (``SO_RXQ_OVFL`` would carry it on every frame, but as it
    was when that frame was queued: the frames already queued when the drops began say 0,
    and nothing says the drops after the last frame). python-can's socketcan bus offers
    neither, hence this class; it offers the ``recv``/``shutdown`` the logger uses."""

    def __init__(self, channel: str, rcvbuf: int = TAP_RCVBUF):
        self.channel = channel
        self.sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        try:
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, rcvbuf)
            except PermissionError:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            self.sock.bind((channel,))
            self._final_drops = self._drops()       # (0; a kernel that cannot count: refused)
        except OSError as exc:
            self.sock.close()
            raise BusError(f"cannot listen on socketcan {channel}: "
                           f"{exc.strerror or exc}") from None
        self.rcvbuf = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    def _drops(self) -> int:
        info = self.sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * 16)
        return struct.unpack_from("=9I", info)[SK_MEMINFO_DROPS]

    @property
    def dropped(self) -> int:
        """Frames the kernel dropped at this socket so far (its receive queue was full); after
        :meth:`shutdown`, the count when it was closed."""
        return self._drops() if self.sock.fileno() >= 0 else self._final_drops

    def recv(self, timeout: Optional[float] = None) -> Optional[can.Message]:
        if not select.select([self.sock], [], [], timeout)[0]:
            return None
        can_id, dlc, data = _CAN_FRAME.unpack(self.sock.recv(_CAN_FRAME.size))
        extended = bool(can_id & socket.CAN_EFF_FLAG)
        return can.Message(
            timestamp=time.time(), channel=self.channel, is_extended_id=extended,
            arbitration_id=can_id & (socket.CAN_EFF_MASK if extended else socket.CAN_SFF_MASK),
            is_remote_frame=bool(can_id & socket.CAN_RTR_FLAG),
            is_error_frame=bool(can_id & socket.CAN_ERR_FLAG), data=data[:min(dlc, 8)])

    def shutdown(self) -> None:
        if self.sock.fileno() >= 0:
            self._final_drops = self._drops()
        self.sock.close()


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

    def open(self, timeout_s: float = 5.0, can_filters: Optional[list[dict]] = None,
             node: Optional[str] = None, secret: Optional[bytes] = None) -> can.BusABC:
        """Open the bus, retrying until ``timeout_s`` (a hub may still be starting).
        ``can_filters`` (python-can's acceptance filters) are applied where the frames are
        fanned out: in the kernel (socketcan) or in the hub (remote), so frames a node does not
        read never reach its process. ``node`` (a DBC node name): on a hub, authenticate as
        that node with the run's secret (``HIL_HUB_SECRET`` in the environment), so the hub
        relays the node's own messages; without it a hub client is read-only. ``secret``: the
        run's secret given directly (a tester's, from the run's hub.secret file)."""
        if self.interface in FORBIDDEN_INTERFACES:
            raise BusError(f"interface {self.interface!r} leaves the machine; not allowed")
        if self.interface == "remote":
            check_remote_url(self.channel)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                extra = {}
                if self.interface == "remote":
                    fast_remote_client()
                    extra = credentials(node, secret)
                bus = can.Bus(interface=self.interface, channel=self.channel,
                              can_filters=can_filters, **extra)
                if self.interface == "remote":
                    _no_delay(bus)
                return bus
            except Exception as exc:  # noqa: BLE001 - every backend raises its own errors
                if type(exc).__name__ == "RemoteError":     # the hub refused: final
                    raise BusError(f"the hub at {self.channel} refused: {exc}") from None
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


def rt_of(base: int, role: str) -> int:
    """The SCHED_FIFO priority of a bench process for a base priority (0: none)."""
    return max(1, min(99, base + RT_OFFSET[role])) if base > 0 else 0


def set_rt_priority(priority: int) -> str:
    """Real-time scheduling for this process: ``SCHED_FIFO`` at ``priority`` (Linux; needs
    root, CAP_SYS_NICE or an rtprio limit), so a 1 ms period is not lost to ordinary
    processes. 0 leaves the scheduling alone. Returns what the process runs with, e.g.
    ``"SCHED_FIFO 50"`` or ``"SCHED_OTHER (SCHED_FIFO refused: ...)"``; never raises."""
    if priority <= 0:
        return "SCHED_OTHER"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError, ValueError) as exc:
        return f"SCHED_OTHER (SCHED_FIFO refused: {exc})"
    return f"SCHED_FIFO {priority}"


def _no_delay(bus: can.BusABC) -> None:
    """Small frames must leave at once: without TCP_NODELAY the client's second frame of a
    tick waits for the ACK of the first (Nagle + delayed ACK, up to 40 ms)."""
    sock = getattr(bus, "socket", None)
    if sock is not None:
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            pass


def fast_remote_client() -> None:
    """Make can_remote's client WebSocket (python-can-remote 0.3.0) cheaper per frame, same
    bytes on the wire: a send masks the payload with one integer XOR instead of a Python loop
    with four ``random.getrandbits`` calls (11.3 us per frame measured here), and a read takes
    what the socket has in one ``recv`` and parses frames from that buffer instead of three
    ``recv`` calls per frame (``wait`` reports a buffered frame as readable). Idempotent."""
    from can_remote import websocket as ws

    if getattr(ws.WebSocket, "_hil_fast", False):
        return

    def send_frame(self, opcode, data=b""):
        frame = wsframe.frame(opcode, data, os.urandom(4) if self.mask else None)
        with self._send_lock:
            if not self.closed:
                self.socket.sendall(frame)

    def _need(self, n):
        buf = self.__dict__.setdefault("_rbuf", bytearray())
        while len(buf) < n:
            chunk = self.socket.recv(65536)
            if not chunk:
                raise ws.WebsocketClosed(1006, "Socket closed unexpectedly")
            buf += chunk
        return buf

    def read_frame(self):
        pos = wsframe.header_size(_need(self, 2)[1])
        opcode, length, mask = wsframe.header(_need(self, pos))
        end = pos + length
        buf = _need(self, end)
        data = bytearray(wsframe.xor(bytes(buf[pos:end]), mask) if mask else buf[pos:end])
        del buf[:end]
        return opcode, data

    def wait(self, timeout=None):
        if self.__dict__.get("_rbuf"):
            return True
        return len(select.select([self.socket], [], [], timeout)[0]) > 0

    ws.WebSocket._hil_original = (ws.WebSocket.send_frame, ws.WebSocket.read_frame,
                                  ws.WebSocket.wait)
    ws.WebSocket.send_frame = send_frame
    ws.WebSocket.read_frame = read_frame
    ws.WebSocket.wait = wait
    ws.WebSocket._hil_fast = True


# the hub's process alive but not yet listening: a Python start-up, which took over 10 s in
# User-mode Linux on a loaded CI host; a hub that exits is reported at once
HUB_START_S = 60.0


class Hub:
    """The bench's CAN hub (``hil.hub``: a single-threaded relay speaking python-can-remote's
    protocol), bound to 127.0.0.1, as a child process that only its owner stops (by PID)."""

    def __init__(self, port: Optional[int] = None, rt_priority: int = 0,
                 secret: Optional[str] = None, allow_external_tx: bool = False,
                 allow_unknown_ids: bool = False, log_path: Optional[Path] = None):
        self.port = port or free_port()
        self.rt_priority = rt_priority
        self.secret = secret                # hex; handed over in the environment only
        self.flags = (["--allow-external-tx"] if allow_external_tx else []) + (
            ["--allow-unknown-ids"] if allow_unknown_ids else [])
        self.log_path = log_path
        self.proc: Optional[subprocess.Popen] = None

    @property
    def url(self) -> str:
        return f"ws://{LOOPBACK}:{self.port}/"

    def start(self, timeout_s: float = HUB_START_S) -> "Hub":
        env = {k: v for k, v in os.environ.items() if k != SECRET_ENV}
        if self.secret:
            env[SECRET_ENV] = self.secret
        err = open(self.log_path, "ab") if self.log_path else subprocess.DEVNULL
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "hil.hub", "-p", str(self.port),
                 "--rt-priority", str(self.rt_priority), *self.flags],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err, env=env,
                start_new_session=True, preexec_fn=die_with_parent)
        finally:
            if self.log_path:
                err.close()
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
        terminate(self.proc)
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout_s)

    def __enter__(self) -> "Hub":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def terminate(proc: subprocess.Popen) -> None:
    """SIGTERM to a process this program started, then SIGCONT: a stopped (SIGSTOP) process
    handles the SIGTERM only once resumed. Never raises."""
    if proc.poll() is None:
        for sig in (signal.SIGTERM, signal.SIGCONT):
            try:
                proc.send_signal(sig)
            except OSError:
                pass


SHUTDOWN_S = 2.0


def close_bus(bus: Optional[can.BusABC], timeout_s: float = SHUTDOWN_S) -> bool:
    """``bus.shutdown()`` in bounded time: can_remote's client waits for the hub's close
    handshake (``recv`` in a loop), forever when the hub is stopped or gone silent; after
    ``timeout_s`` the socket is shut down under it. Never raises; False if it had to force."""
    if bus is None:
        return True

    def run():
        try:
            bus.shutdown()
        except Exception:  # noqa: BLE001 - the hub may already be gone
            try:    # (python-can's flag: else its __del__ retries and prints a traceback)
                bus._is_shutdown = True
            except AttributeError:
                pass

    t = threading.Thread(target=run, daemon=True, name="bus-shutdown")
    t.start()
    t.join(timeout_s)
    if not t.is_alive():
        return True
    sock = getattr(bus, "socket", None)
    if sock is not None:
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        try:
            sock.close()
        except OSError:
            pass
    t.join(1.0)
    try:
        bus._is_shutdown = True         # (python-can's flag: no second attempt at exit)
    except AttributeError:
        pass
    return False


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
