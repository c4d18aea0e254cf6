"""The bench's CAN hub: ``python -m hil.hub -p PORT``.

A broadcast relay that speaks python-can-remote's protocol, so every ``-i remote -c
ws://127.0.0.1:PORT/`` client works with it unchanged (the bench's nodes, ``python -m
can.logger``, ``python -m can.viewer``): an HTTP upgrade to a WebSocket with the
``can.binary+json.v1`` (or ``can.json.v1``) subprotocol, a ``bus_request`` answered by a
``bus_response``, then CAN frames both ways. Like python-can's ``virtual`` bus behind
can_remote's server, a frame goes to every other client whose acceptance filters
(``can_filters`` of its bus request) let it through, never back to its sender, stamped with the
hub's clock when it arrives.

Why not can_remote's own server: it runs two threads per client and hands every frame from
the sender's thread to a queue and then to each receiver's thread, and those wake-ups cost
more than the work (a ping-pong through it took 253 us p50 / 402 us p99 with four clients
here). This hub is one thread around ``selectors``: it reads a frame and writes it to the
receivers' sockets at once (nonblocking; a slow client's backlog is kept, up to
``MAX_BACKLOG`` bytes, after which that client is dropped so it cannot stall the others).
It listens on 127.0.0.1 only. Periodic transmission in the hub (``periodic_start``) is not
supported and answered with an error event.

Every client message is validated before it is used: a WebSocket message larger than
``MAX_MESSAGE`` bytes (refused from its length header, before it is buffered), a binary frame
shorter than its header, JSON that is not an event object, a frame whose ID is outside the
standard (11-bit) or extended (29-bit) range, whose DLC or data length is not a CAN (FD) one,
whose data is not a list of bytes or whose flags are not booleans: each disconnects that client,
with the reason in the hub's log (stderr) and an ``error`` event to the client; the hub and the
other clients go on. A client may send at most ``RATE_LIMIT_FPS`` frames per second (a token
bucket with one second of burst); frames beyond that are dropped and counted, and the count is
logged when the client leaves.

Who may send (``hil.transport.auth``): a hub started with a secret (``HIL_HUB_SECRET`` in its
environment, as ``hil run`` starts it) relays a client's frames only when the client
authenticated as a bench node in its bus request and the frame is one the DBC names that node
the transmitter of. Other clients (``can.logger``, ``can.viewer``, ``cantools monitor``) are
read-only: they receive everything, and what they send is dropped and counted
(``--allow-external-tx`` lets them send, for injection tests; ``--allow-unknown-ids`` lets
nodes send IDs outside the DBC, for the fault campaign). A wrong token disconnects. A hub
started by hand without a secret lets every client send, and says so.
"""

from __future__ import annotations

import argparse
import hmac
import json
import selectors
import signal
import socket
import sys
import time
from typing import Optional

from hil.transport import auth
from hil.transport import wsframe as ws
from hil.transport.hubproto import (BIN_MSG, BIN_TYPE, IS_EXTENDED_ID, BadMessage, Frame,
                                    checked_frame, frame_from_json, parse_filters)

LOOPBACK = "127.0.0.1"
CHANNEL_INFO = "hil.hub broadcast relay"
MAX_BACKLOG = 16 * 1024 * 1024      # bytes queued for one client before it is dropped
MAX_HEADER = 16 * 1024              # an HTTP request head larger than this is refused
MAX_MESSAGE = 4096                  # a larger WebSocket message disconnects its client
RATE_LIMIT_FPS = 100_000            # frames per second one client may send (plant and ECU
#                                     send 1,210 per simulated second, 3,700/s in lockstep)
_TEXT, _BINARY, _CLOSE, _PING, _PONG = ws.TEXT, ws.BINARY, ws.CLOSE, ws.PING, ws.PONG


class Client:
    __slots__ = ("sock", "inbuf", "out", "state", "binary", "filters", "name", "closing",
                 "tokens", "t_tokens", "rate_dropped", "node", "may_send", "denied")

    def __init__(self, sock: socket.socket, name: str):
        self.sock = sock
        self.inbuf = bytearray()
        self.out = bytearray()          # bytes the socket did not take yet
        self.state = "http"             # http -> request (bus_request expected) -> bus
        self.binary = True
        self.filters: Optional[list[tuple[int, int, Optional[bool]]]] = None
        self.name = name
        self.closing = False
        self.tokens = float("inf")            # the rate limit's bucket (frames; full)
        self.t_tokens = time.monotonic()
        self.rate_dropped = 0                  # frames dropped for the rate limit
        self.node: Optional[str] = None        # the DBC node it authenticated as
        self.may_send = None                   # IDs it may send (None: any)
        self.denied = 0                        # frames dropped: not its to send

    def within_rate(self, rate: float) -> bool:
        """Take one frame from the bucket (refilled at ``rate`` per second, one second deep)."""
        now = time.monotonic()
        self.tokens = min(rate, self.tokens + (now - self.t_tokens) * rate)
        self.t_tokens = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        self.rate_dropped += 1
        return False

    def accepts(self, f: Frame) -> bool:
        """python-can's acceptance filter rule (BusABC._matches_filters)."""
        if not self.filters:
            return True
        for can_id, mask, ext in self.filters:
            if ext is not None and ext != bool(f.flags & IS_EXTENDED_ID):
                continue
            if (can_id ^ f.arb_id) & mask == 0:
                return True
        return False


class HubServer:
    def __init__(self, port: int, host: str = LOOPBACK, log=None,
                 max_backlog: int = MAX_BACKLOG, rate_limit_fps: float = RATE_LIMIT_FPS,
                 secret: Optional[bytes] = None, senders: Optional[dict] = None,
                 allow_external_tx: bool = False, allow_unknown_ids: bool = False):
        if host != LOOPBACK:
            raise ValueError("the hub listens on 127.0.0.1 only")
        # who may send what: with a secret, a client that authenticates as a DBC node may
        # send that node's messages (``senders``: node -> frame IDs), any other is read-only
        self.secret = secret
        self.senders = senders or {}
        self.known_ids = frozenset().union(*self.senders.values()) if self.senders else None
        self.allow_external_tx = allow_external_tx
        self.allow_unknown_ids = allow_unknown_ids
        self.denied_frames = 0
        self.sel = selectors.DefaultSelector()
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((host, port))
        self.listener.listen(16)
        self.listener.setblocking(False)
        self.sel.register(self.listener, selectors.EVENT_READ, None)
        self.clients: list[Client] = []
        self.frames_relayed = 0
        self.dropped_clients = 0
        self.rejected_clients = 0           # disconnected for a bad message
        self.rate_limit_fps = float(rate_limit_fps)
        self.running = True
        self.max_backlog = max_backlog
        self.log = log or (lambda msg: None)

    @property
    def port(self) -> int:
        return self.listener.getsockname()[1]

    # -- event loop ----------------------------------------------------------------------
    def serve_forever(self) -> None:
        while self.running:
            for key, mask in self.sel.select(0.2):
                if key.data is None:
                    self._accept()
                    continue
                c: Client = key.data
                if mask & selectors.EVENT_WRITE:
                    self._flush(c)
                if mask & selectors.EVENT_READ and c in self.clients:
                    self._read(c)

    def close(self) -> None:
        for c in list(self.clients):
            self._drop(c)
        self.sel.unregister(self.listener)
        self.listener.close()
        self.sel.close()

    def _accept(self) -> None:
        try:
            sock, addr = self.listener.accept()
        except OSError:
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        c = Client(sock, f"{addr[0]}:{addr[1]}")
        self.clients.append(c)
        self.sel.register(sock, selectors.EVENT_READ, c)

    def _reject(self, c: Client, reason: str) -> None:
        """A bad message: tell the client, log the reason, disconnect it."""
        self.log(f"disconnecting {c.name}: {reason}")
        self.rejected_clients += 1
        if c.state != "http":
            self._event(c, "error", f"disconnected: {reason}")
        self._drop(c)

    def _drop(self, c: Client) -> None:
        if c in self.clients:
            if c.denied:
                self.log(f"{c.name}{'' if c.node else ' (read-only)'}: {c.denied} frames "
                         f"it may not send dropped")
            if c.rate_dropped:
                self.log(f"{c.name}: {c.rate_dropped} frames over the rate limit "
                         f"({self.rate_limit_fps:g}/s) dropped")
            self.clients.remove(c)
            try:
                self.sel.unregister(c.sock)
            except (KeyError, ValueError):
                pass
            c.sock.close()

    # -- output --------------------------------------------------------------------------
    def _send(self, c: Client, data: bytes) -> None:
        if c.out:
            c.out += data
            if len(c.out) > self.max_backlog:
                self.log(f"dropping {c.name}: {len(c.out)} bytes not read")
                self.dropped_clients += 1
                self._drop(c)
            return
        try:
            n = c.sock.send(data)
        except BlockingIOError:
            n = 0
        except OSError:
            self._drop(c)
            return
        if n < len(data):
            c.out += data[n:]
            self.sel.modify(c.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, c)

    def _flush(self, c: Client) -> None:
        try:
            n = c.sock.send(c.out)
        except BlockingIOError:
            return
        except OSError:
            self._drop(c)
            return
        del c.out[:n]
        if not c.out:
            if c.closing:
                self._drop(c)
            else:
                self.sel.modify(c.sock, selectors.EVENT_READ, c)

    def _event(self, c: Client, kind: str, payload) -> None:
        self._send(c, ws.frame(_TEXT, json.dumps({"type": kind, "payload": payload}).encode()))

    # -- input ---------------------------------------------------------------------------
    def _read(self, c: Client) -> None:
        try:
            chunk = c.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(c)
            return
        c.inbuf += chunk
        if c.state == "http":
            self._handshake(c)
        if c.state != "http" and c in self.clients:
            self._frames(c)

    def _handshake(self, c: Client) -> None:
        end = c.inbuf.find(b"\r\n\r\n")
        if end < 0:
            if len(c.inbuf) > MAX_HEADER:
                self._drop(c)
            return
        head = bytes(c.inbuf[:end]).decode("latin-1").split("\r\n")
        del c.inbuf[:end + 4]
        headers = {}
        for line in head[1:]:
            k, _, v = line.partition(":")
            headers[k.strip().lower()] = v.strip()
        key = headers.get("sec-websocket-key")
        if headers.get("upgrade", "").lower() != "websocket" or not key:
            body = (b"python -m hil.hub: a python-can remote hub; connect with "
                    b"-i remote -c ws://127.0.0.1:PORT/\n")
            self._send(c, b"HTTP/1.1 404 Not Found\r\nContent-Type: text/plain\r\n"
                       b"Content-Length: %d\r\nConnection: close\r\n\r\n" % len(body) + body)
            c.closing = True
            if not c.out:
                self._drop(c)
            return
        offered = [p.strip() for p in headers.get("sec-websocket-protocol",
                                                  "can.json.v1").split(",")]
        c.binary = "can.binary+json.v1" in offered
        proto = "can.binary+json.v1" if c.binary else "can.json.v1"
        self._send(c, ("HTTP/1.1 101 Switching Protocols\r\nUpgrade: WebSocket\r\n"
                       "Connection: Upgrade\r\n"
                       f"Sec-WebSocket-Accept: {ws.accept_key(key)}\r\n"
                       f"Sec-WebSocket-Protocol: {proto}\r\n\r\n").encode())
        c.state = "request"

    def _frames(self, c: Client) -> None:
        buf = c.inbuf
        while len(buf) >= 2 and c in self.clients:
            pos = ws.header_size(buf[1])
            if len(buf) < pos:
                return
            opcode, n, mask = ws.header(buf)
            if n > MAX_MESSAGE:
                self._reject(c, f"a {n}-byte message (at most {MAX_MESSAGE})")
                return
            need = pos + n
            if len(buf) < need:
                return
            payload = ws.xor(bytes(buf[pos:need]), mask) if mask else bytes(buf[pos:need])
            del buf[:need]
            self._message(c, opcode, payload)

    def _message(self, c: Client, opcode: int, payload: bytes) -> None:
        if opcode == _BINARY:
            if c.state != "bus":
                self._reject(c, "a binary message before the bus request")
            elif len(payload) < 1 + BIN_MSG.size or payload[0] != BIN_TYPE:
                self._reject(c, f"a malformed binary message ({len(payload)} bytes)")
            else:
                _ts, arb_id, dlc, flags = BIN_MSG.unpack_from(payload, 1)
                try:
                    frame = checked_frame(arb_id, dlc, flags, payload[1 + BIN_MSG.size:])
                except BadMessage as exc:
                    self._reject(c, f"bad frame: {exc}")
                    return
                if self._may_send(c, frame) and c.within_rate(self.rate_limit_fps):
                    self.relay(c, frame)
            return
        if opcode == _TEXT:
            try:
                event = json.loads(payload)
                kind = event["type"] if isinstance(event, dict) else None
            except (ValueError, KeyError, RecursionError):
                kind = None
            if not isinstance(kind, str):
                self._reject(c, "not a JSON event with a 'type'")
                return
            if c.state == "request":
                if kind != "bus_request":
                    self._event(c, "error", "expected a bus_request")
                    return
                try:
                    cfg = event.get("payload", {}).get("config", {}) or {}
                    c.filters = parse_filters(cfg.get("can_filters"))
                except (AttributeError, KeyError, TypeError, ValueError, OverflowError) as exc:
                    self._reject(c, f"bad bus_request: {exc}")
                    return
                if not self._authorise(c, cfg):
                    return
                c.state = "bus"
                self._event(c, "bus_response", {"channel_info": CHANNEL_INFO})
            elif kind == "message":
                try:
                    frame = frame_from_json(event.get("payload"))
                except BadMessage as exc:
                    self._reject(c, f"bad message: {exc}")
                    return
                if self._may_send(c, frame) and c.within_rate(self.rate_limit_fps):
                    self.relay(c, frame)
            else:
                self._event(c, "error", f"{kind!r} is not supported by this hub")
            return
        if opcode == _PING:
            self._send(c, ws.frame(_PONG, payload))
        elif opcode == _CLOSE:
            self._send(c, ws.frame(_CLOSE, payload[:2]))
            c.closing = True
            try:
                c.sock.shutdown(socket.SHUT_RD)
            except OSError:
                pass
            if not c.out:
                self._drop(c)

    def _authorise(self, c: Client, cfg: dict) -> bool:
        """Set what the client may send from its bus request: ``hil_node`` and ``hil_token``
        (HMAC-SHA256 of the node name under the run's secret) make it that DBC node; without
        them it is read-only (``allow_external_tx``: it may send anything); a wrong token
        disconnects it. Without a secret (a hub started by hand) every client may send."""
        if self.secret is None:
            return True
        node, token = cfg.get("hil_node"), cfg.get("hil_token")
        if node is None and token is None:
            c.may_send = None if self.allow_external_tx else frozenset()
            return True
        if not (isinstance(node, str) and isinstance(token, str) and node in self.senders
                and hmac.compare_digest(token, auth.node_token(self.secret, node))):
            self._reject(c, f"authentication as {node!r} failed")
            return False
        c.node = node
        c.may_send = self.senders[node]
        c.name = f"{c.name} {node}"
        return True

    def _may_send(self, c: Client, frame: Frame) -> bool:
        allowed = c.may_send
        if allowed is None or frame.arb_id in allowed or (
                self.allow_unknown_ids and c.node is not None
                and frame.arb_id not in self.known_ids):
            return True
        if not c.denied:
            self.log(f"{c.name}{'' if c.node else ' (read-only)'} may not send "
                     f"0x{frame.arb_id:X}: dropped (and every further frame it may not send)")
        c.denied += 1
        self.denied_frames += 1
        return False

    def relay(self, src: Client, frame: Frame) -> None:
        """Send a frame to every other client on the bus whose filters accept it."""
        ts = time.time()
        binary = text = None
        self.frames_relayed += 1
        for c in tuple(self.clients):
            if c is src or c.state != "bus" or c.closing or not c.accepts(frame):
                continue
            if c.binary:
                if binary is None:
                    binary = frame.binary(ts)
                self._send(c, binary)
            else:
                if text is None:
                    text = frame.json(ts)
                self._send(c, text)


def main(argv: list[str] | None = None) -> int:
    import os

    ap = argparse.ArgumentParser("python -m hil.hub", description=__doc__.splitlines()[0])
    ap.add_argument("-p", "--port", type=int, required=True)
    ap.add_argument("--rt-priority", type=int, default=0, metavar="N",
                    help="SCHED_FIFO priority (0: normal scheduling)")
    ap.add_argument("--allow-external-tx", action="store_true",
                    help="clients that do not authenticate may send (injection tests)")
    ap.add_argument("--allow-unknown-ids", action="store_true",
                    help="nodes may also send IDs the DBC does not define (the fault "
                         "campaign's babbling sender)")
    args = ap.parse_args(argv)
    secret = os.environ.pop(auth.SECRET_ENV, None)
    try:
        key = bytes.fromhex(secret) if secret else None
    except ValueError:
        print(f"hil.hub: {auth.SECRET_ENV} is not hex", file=sys.stderr)
        return 2
    if args.rt_priority:
        from hil.transport.bus import set_rt_priority

        got = set_rt_priority(args.rt_priority)
        if not got.startswith("SCHED_FIFO"):
            print(f"hil.hub: {got}", file=sys.stderr)
    log = (lambda m: print(f"hil.hub: {m}", file=sys.stderr, flush=True))
    try:
        senders = auth.dbc_senders() if key else None
    except ValueError as exc:          # (hil.transport.codec.DbcError: a broken DBC, one line)
        log(str(exc))
        return 2
    if secret is None:
        log(f"no {auth.SECRET_ENV} in the environment: every client may send anything")
    server = HubServer(args.port, log=log,
                       secret=key, senders=senders,
                       allow_external_tx=args.allow_external_tx,
                       allow_unknown_ids=args.allow_unknown_ids)

    def stop(*_):
        server.running = False

    signal.signal(signal.SIGTERM, stop)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
