"""UDS over ISO-TP: the ECU node's transport around the firmware's dispatch, and the tester.

* ``UdsServer`` (in the ECU node): can-isotp's ``TransportLayerLogic`` driven by the node, no
  thread. The node feeds it the DIAG_REQUEST frames and sends the frames it returns;
  ``firmware.diag.uds.handle`` answers each complete request. It runs between control ticks, in
  the node's receive path, and never touches the control state: a reset (0x11) is carried out
  by the node after its response is queued.
* ``python -m hil diag``: a tester on **udsoncan** (with can-isotp under it) that reads the
  ECU's identification and live DIDs, its DTCs with status, snapshot and extended data, and
  clears them (``--clear``), from a running bench: the hub (``-i remote -c ws://...``, with
  ``--secret-file DIR/hub.secret`` to authenticate as the DBC's TESTER, the only sender of
  DIAG_REQUEST) or vcan0. A table, or ``--json``.
"""

from __future__ import annotations

import json
from collections import deque
from typing import Callable, Optional

REQUEST_ID, RESPONSE_ID = 0x7E0, 0x7E8      # DIAG_REQUEST, DIAG_RESPONSE (dbc/suspension.dbc)
PADDING = 0xCC
ISOTP_PARAMS = {
    "stmin": 0, "blocksize": 0, "tx_data_length": 8, "tx_data_min_length": 8,
    "tx_padding": PADDING, "rx_flowcontrol_timeout": 1000, "rx_consecutive_frame_timeout": 1000,
    "max_frame_size": 4095, "can_fd": False, "blocking_send": False, "wftmax": 0,
}
INBOX_FRAMES = 256          # frames of a request not yet processed (bounded)


class UdsServer:
    """ISO-TP on the ECU's diagnostic IDs around ``handle(request) -> response | None``."""

    def __init__(self, handle: Callable[[bytes], Optional[bytes]]):
        import isotp

        self._isotp = isotp
        self.handle = handle
        self._in: deque = deque(maxlen=INBOX_FRAMES)
        self._out: list = []
        self.requests = 0
        self.errors = 0             # ISO-TP errors (bad frames, timeouts) from the tester side
        addr = isotp.Address(isotp.AddressingMode.Normal_11bits, txid=RESPONSE_ID,
                             rxid=REQUEST_ID)
        self.tp = isotp.TransportLayerLogic(rxfn=self._rx, txfn=self._tx, address=addr,
                                            error_handler=self._error, params=ISOTP_PARAMS)

    def _rx(self, timeout: float):
        return self._in.popleft() if self._in else None

    def _tx(self, msg) -> None:
        self._out.append((msg.arbitration_id, bytes(msg.data)))

    def _error(self, exc) -> None:
        self.errors += 1

    def on_frame(self, data: bytes) -> list:
        """A DIAG_REQUEST frame: the frames to send in answer (flow control, a response)."""
        self._in.append(self._isotp.CanMessage(arbitration_id=REQUEST_ID, data=data))
        return self.poll()

    @property
    def busy(self) -> bool:
        """A transfer is under way (its timers need ``poll``)."""
        return self.tp.transmitting() or self.tp.rx_state != self.tp.RxState.IDLE

    def poll(self) -> list:
        tp = self.tp
        tp.process()
        while tp.available():
            req = tp.recv()
            self.requests += 1
            resp = self.handle(bytes(req))
            if resp:
                tp.send(resp)
                tp.process()
        out, self._out = self._out, []
        return out


# ---------------------------------------------------------------- the tester


def _codecs() -> dict:
    from udsoncan import DidCodec

    from firmware.diag import uds

    class Raw(DidCodec):
        def __init__(self, n: int):
            self.n = n

        def encode(self, *args, **kwargs):    # (the tester only reads)
            raise NotImplementedError

        def decode(self, payload: bytes):
            return bytes(payload)

        def __len__(self) -> int:
            return self.n

    sizes = {uds.DID_SOFTWARE_VERSION: uds.SOFTWARE_VERSION_LEN, uds.DID_CALIBRATION_SHA256: 32,
             uds.DID_VEHICLE_SHA256: 32, uds.DID_ACTIVE_MODE: 1, uds.DID_GRADE: 1,
             uds.DID_SUPPLY_VOLTAGE: 2, uds.DID_FAULT_WORD: 4, uds.DID_BA_RMS: 2,
             uds.DID_DTD_RMS: 2, uds.DID_TICK: 4, uds.DID_DEGRADED: 10,
             uds.DID_SNAPSHOT: uds.SNAPSHOT_SIZE}
    return {did: Raw(n) for did, n in sizes.items()}


def dtc_label(code: int) -> str:
    """The 3-byte DTC as SAE J2012 text: 'C1001-29'."""
    hi = code >> 8
    return f"{'PCBU'[hi >> 14]}{hi & 0x3FFF:04X}-{code & 0xFF:02X}"


STATUS_BITS = ("testFailed", "testFailedThisOperationCycle", "pendingDTC", "confirmedDTC",
               "testNotCompletedSinceLastClear", "testFailedSinceLastClear",
               "testNotCompletedThisOperationCycle", "warningIndicatorRequested")
REPORTED = 0x2F     # DTCs with any of TF, TFTOC, PDTC, CDTC, TFSLC


def read_all(client, clear: bool = False) -> dict:
    """Identification and live DIDs, then every DTC that failed since the last clear with its
    snapshot and extended data; then clear them when asked."""
    return {"ecu": read_dids(client), **read_dtcs(client, clear)}


def read_dids(client) -> dict:
    from firmware.diag import uds
    from firmware.params import GRADE_NAMES, MODE_NAMES

    dids: dict = {}
    n = uds.MAX_DIDS_PER_REQUEST
    for k in range(0, len(uds.DIDS), n):
        resp = client.read_data_by_identifier(list(uds.DIDS[k:k + n]))
        dids.update(resp.service_data.values)
    u16 = lambda b: int.from_bytes(b, "big")   # noqa: E731
    grade = dids[uds.DID_GRADE][0]
    mode = dids[uds.DID_ACTIVE_MODE][0]
    supply = u16(dids[uds.DID_SUPPLY_VOLTAGE])
    ident = {
        "software_version": dids[uds.DID_SOFTWARE_VERSION].rstrip(b"\0").decode("ascii", "replace"),
        "calibration_sha256": dids[uds.DID_CALIBRATION_SHA256].hex(),
        "vehicle_sha256": dids[uds.DID_VEHICLE_SHA256].hex(),
        "active_mode": MODE_NAMES[mode] if mode < len(MODE_NAMES) else mode,
        "grade": GRADE_NAMES[grade] if grade < len(GRADE_NAMES) else "unknown",
        "supply_voltage_v": None if supply == 0xFFFF else supply / 1000,
        "fault_word": u16(dids[uds.DID_FAULT_WORD]),
        "ba_rms_mps2": u16(dids[uds.DID_BA_RMS]) / 1000, "dtd_rms_m": u16(dids[uds.DID_DTD_RMS]) / 1e6,
        "tick": int.from_bytes(dids[uds.DID_TICK], "big"),
        "degraded": _degraded(dids[uds.DID_DEGRADED])}
    return ident


def _degraded(raw: bytes) -> dict:
    """DID 0x0107 (firmware.diag.uds): the degraded state, the sensor out, the ticks."""
    from firmware.diag.degrade import SENSOR_NAMES, STATE_NAMES

    none = 0xFFFFFFFF
    since, second = int.from_bytes(raw[2:6], "big"), int.from_bytes(raw[6:10], "big")
    return {"state": STATE_NAMES[raw[0]] if raw[0] < len(STATE_NAMES) else raw[0],
            "sensor_out": SENSOR_NAMES[raw[1]] if raw[1] < len(SENSOR_NAMES) else None,
            "since_tick": None if since == none else since,
            "second_fault_tick": None if second == none else second}


def read_dtcs(client, clear: bool = False) -> dict:
    """Every DTC that failed since the last clear, with status, snapshot and extended data;
    then cleared when asked."""
    from firmware.diag import dtc as fw_dtc
    from firmware.diag import uds
    from firmware.params import GRADE_NAMES, MODE_NAMES

    u16 = lambda b: int.from_bytes(b, "big")   # noqa: E731
    listed = client.get_dtc_by_status_mask(REPORTED).service_data.dtcs
    dtcs = []
    for d in listed:
        entry = {"code": dtc_label(d.id), "id": d.id,
                 "name": fw_dtc.DTCS[fw_dtc.BY_CODE[d.id]].name if d.id in fw_dtc.BY_CODE else "?",
                 "status": d.status.get_byte_as_int(),
                 "status_bits": [n for i, n in enumerate(STATUS_BITS)
                                 if d.status.get_byte_as_int() >> i & 1]}
        snap = client.get_dtc_snapshot_by_dtc_number(d.id, uds.SNAPSHOT_RECORD).service_data
        for s in snap.dtcs[0].snapshots if snap.dtcs else ():
            raw = s.data
            g, m = raw[6], raw[7]
            entry["snapshot"] = {
                "tick": int.from_bytes(raw[0:4], "big"),
                "speed_mps": None if u16(raw[4:6]) == 0xFFFF else u16(raw[4:6]) / 100,
                "grade": GRADE_NAMES[g] if g < len(GRADE_NAMES) else "unknown",
                "mode": MODE_NAMES[m] if m < len(MODE_NAMES) else m,
                "ba_rms_mps2": u16(raw[8:10]) / 1000, "dtd_rms_m": u16(raw[10:12]) / 1e6,
                "supply_voltage_v": None if u16(raw[12:14]) == 0xFFFF else u16(raw[12:14]) / 1000}
        ext = client.get_dtc_extended_data_by_dtc_number(d.id, 0xFF, data_size=1).service_data
        for e in ext.dtcs[0].extended_data if ext.dtcs else ():
            key = {1: "occurrences", 2: "fdc", 3: "aging_cycles"}.get(e.record_number)
            if key:
                v = e.raw_data[0]
                entry[key] = v - 256 if key == "fdc" and v > 127 else v
        dtcs.append(entry)
    out = {"dtcs": dtcs, "cleared": False}
    if clear:
        client.clear_dtc(0xFFFFFF)
        out["cleared"] = True
    return out


def render(doc: dict) -> str:
    from io import StringIO

    from rich.console import Console
    from rich.table import Table

    buf = StringIO()
    con = Console(file=buf, width=120, color_system=None)
    t = Table(title="ECU", show_header=False)
    for k, v in doc["ecu"].items():
        t.add_row(k, "not measured" if v is None else str(v))
    con.print(t)
    if not doc["dtcs"]:
        con.print("DTCs: none failed since the last clear")
    else:
        t = Table(title="DTCs failed since the last clear")
        for col in ("DTC", "name", "status", "occ", "snapshot (tick, speed, grade, mode, BA, DTD)"):
            t.add_column(col)
        for d in doc["dtcs"]:
            s = d.get("snapshot")
            speed = "?" if s["speed_mps"] is None else f"{s['speed_mps']:.2f}"
            snap = (f"{s['tick']}, {speed} m/s, {s['grade']}, {s['mode']}, "
                    f"{s['ba_rms_mps2']:.3f} m/s2, {s['dtd_rms_m'] * 1e3:.2f} mm") if s else "-"
            t.add_row(d["code"], d["name"], f"0x{d['status']:02X}", str(d.get("occurrences", "")),
                      snap)
        con.print(t)
    if doc["cleared"]:
        con.print("DTCs cleared")
    return buf.getvalue().rstrip()


def add_parser(sub) -> None:
    from can.cli import add_bus_arguments

    p = sub.add_parser("diag", help="UDS tester (udsoncan): read the ECU's DIDs and DTCs "
                                    "with snapshots from a running bench, --clear them")
    add_bus_arguments(p)
    p.add_argument("--secret-file", metavar="FILE",
                   help="the run's hub secret (hil run writes DIR/hub.secret): authenticates "
                        "the tester as the DBC's TESTER on a hub")
    p.add_argument("--clear", action="store_true", help="clear every DTC after reading")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S",
                   help="seconds to wait for each response (default: 2)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def open_tester_bus(interface, channel, secret_file, response_id: int = RESPONSE_ID):
    from hil.transport.bus import BusError, resolve
    from hil.cli import fail
    from hil.config import ConfigError
    from hil.transport.secoc import load_key

    try:
        spec, needs_hub = resolve(interface, channel)
    except BusError as exc:
        fail(str(exc))
    if needs_hub:
        fail("no bench to talk to: give the hub with -i remote -c ws://127.0.0.1:PORT/ (hil "
             "run prints it), or run on vcan0")
    secret = None
    if spec.interface == "remote":
        if not secret_file:
            fail("on a hub the tester needs --secret-file DIR/hub.secret (else it is read-only)")
        try:
            secret = load_key(secret_file, "the hub's secret: hil run writes it as "
                              "OUT/hub.secret, OUT its --out, default out/run")
        except ConfigError as exc:
            fail(f"--secret-file: {exc}")
    try:
        return tester_bus(spec, secret, response_id)
    except BusError as exc:          # (nothing behind the bus given: the run's failure, not
        fail(str(exc), 1)            #  its input, as a bench that gives no answer)


def tester_bus(spec, secret: Optional[bytes] = None, response_id: int = RESPONSE_ID):
    """The tester's bus: its responses only (DIAG_RESPONSE; XCP_RES for the XCP tool),
    authenticated as TESTER (on a hub, with the run's secret)."""
    return spec.open(can_filters=[{"can_id": response_id, "can_mask": 0x7FF,
                                   "extended": False}], node="TESTER", secret=secret)


def client(bus, timeout: float):
    """A udsoncan client over can-isotp on the diagnostic IDs (use it as a context)."""
    import isotp
    import udsoncan
    from udsoncan.client import Client
    from udsoncan.connections import PythonIsoTpConnection

    addr = isotp.Address(isotp.AddressingMode.Normal_11bits, txid=REQUEST_ID, rxid=RESPONSE_ID)
    stack = isotp.CanStack(bus, address=addr, params=ISOTP_PARAMS)
    config = dict(udsoncan.configs.default_client_config)
    config.update(data_identifiers=_codecs(), request_timeout=timeout, p2_timeout=timeout,
                  p2_star_timeout=timeout, use_server_timing=False)
    return Client(PythonIsoTpConnection(stack), config=config)


# the protocol libraries' loggers (can-isotp, udsoncan): their warnings went to stderr
# through logging's last resort beside the tool's own line (two isotp lines when the tester
# was started before the ECU answered); what they report reaches the tool as an exception
PROTOCOL_LOGGERS = ("isotp", "UdsClient", "Connection")


def quiet_protocol_logs() -> None:
    """The protocol libraries say nothing on stderr: the tool's one line says what failed."""
    import logging

    for name in PROTOCOL_LOGGERS:
        log = logging.getLogger(name)
        log.addHandler(logging.NullHandler())
        log.propagate = False


def main(args) -> int:
    import udsoncan

    from hil.transport.bus import close_bus
    from hil.cli import fail

    if not 0 < args.timeout <= 60:
        fail("--timeout must be in (0, 60] s")
    quiet_protocol_logs()
    # (python-can's bus options leave -i and -c unset unless given)
    bus = open_tester_bus(getattr(args, "interface", None), getattr(args, "channel", None),
                          args.secret_file)
    try:
        with client(bus, args.timeout) as c:
            doc = read_all(c, clear=args.clear)
    except udsoncan.exceptions.TimeoutException:
        fail(f"no answer from the ECU within {args.timeout:g} s (is the bench running? its "
             "ECU answers once the drive has started, a few seconds after hil run prints its "
             "bus)", 1)
    except udsoncan.exceptions.NegativeResponseException as exc:
        fail(f"the ECU refused: {exc}", 1)
    except (udsoncan.exceptions.InvalidResponseException,
            udsoncan.exceptions.UnexpectedResponseException) as exc:
        fail(f"bad response from the ECU: {exc}", 1)
    finally:
        close_bus(bus)
    print(json.dumps(doc, indent=1) if args.json else render(doc))
    return 0
