"""The commands of ``python -m hil xcp`` (``hil.apps.xcptool`` has the pieces)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calib.a2l import EVENTS
from hil.apps import xcptool as xt

EVENT_NAMES = {short: ch for _, short, ch, _ in EVENTS}


def add_parser(sub) -> None:
    from can.cli import add_bus_arguments

    p = sub.add_parser("xcp", help="XCP calibration tool (pyxcp): read, write and measure "
                                   "the ECU of a running bench by its A2L")
    verbs = p.add_subparsers(dest="verb", required=True)
    for verb, text in (("info", "connect, check the EPK, unlock: the slave's facts"),
                       ("get", "read an object (physical values)"),
                       ("set", "write a calibration object (physical values)"),
                       ("measure", "DAQ of measurements to an MF4 file"),
                       ("save", "the working page as a design file (--design reads it)")):
        v = verbs.add_parser(verb, help=text)
        add_bus_arguments(v)
        v.add_argument("--secret-file", metavar="FILE",
                       help="the run's hub secret (DIR/hub.secret): on a hub, authenticates "
                            "the tool as the DBC's TESTER")
        v.add_argument("--key-file", metavar="FILE", required=True,
                       help="the run's key file (DIR/secoc.key): the seed-and-key secret")
        v.add_argument("--a2l", metavar="FILE", default=str(xt.A2L_PATH),
                       help="the ECU's A2L (default: c/generated/ecu.a2l)")
        v.add_argument("--timeout", type=float, default=2.0, metavar="S",
                       help="seconds to wait for a response (default: 2)")
        v.add_argument("--json", action="store_true", help="one JSON object on stdout")
        if verb in ("get", "set"):
            v.add_argument("name", metavar="NAME")
        if verb == "set":
            v.add_argument("value", metavar="VALUE", help="a number, or one per element, "
                                                          "comma-separated")
        if verb == "save":
            v.add_argument("file", metavar="FILE.toml")
            v.add_argument("--design", metavar="BASE", default=None,
                           help="the run's design file: its [design] table is kept and its "
                                "[calibration] table is the base of the one written")
        if verb == "measure":
            v.add_argument("names", metavar="NAME", nargs="+")
            v.add_argument("--event", choices=sorted(EVENT_NAMES), default="10ms")
            v.add_argument("--prescaler", type=int, default=1, metavar="N")
            v.add_argument("--seconds", type=float, required=True, metavar="S",
                           help="of the ECU's time")
            v.add_argument("--out", metavar="FILE.mf4", required=True)


def _open(args):
    from hil.apps.diag import open_tester_bus
    from hil.cli import fail
    from hil.config import ConfigError
    from hil.transport.codec import Codec
    from hil.transport.secoc import load_key

    if not 0 < args.timeout <= 60:
        fail("--timeout must be in (0, 60] s")
    try:
        key = load_key(args.key_file)
    except ConfigError as exc:
        fail(f"--key-file: {exc}")
    try:
        a2l = xt.A2l(Path(args.a2l))
    except (FileNotFoundError, KeyError, ValueError) as exc:
        fail(f"--a2l: {exc}")
    bus = open_tester_bus(getattr(args, "interface", None), getattr(args, "channel", None),
                          args.secret_file, response_id=Codec().message("XCP_RES").frame_id)
    return key, a2l, bus


def main(args) -> int:
    from pyxcp.types import XcpResponseError, XcpTimeoutError

    from hil.cli import fail
    from hil.transport.bus import close_bus
    from hil.xcp.protocol import ERROR_NAMES

    key, a2l, bus = _open(args)
    try:
        items = [a2l.item(n) for n in getattr(args, "names", None) or
                 ([args.name] if getattr(args, "name", None) else [])]
    except KeyError as exc:
        close_bus(bus)
        fail(str(exc.args[0]))
    try:
        doc = _VERBS[args.verb](args, key, a2l, bus, items)
    except XcpResponseError as exc:
        code = int(exc.get_error_code())
        fail(f"the ECU refused: {ERROR_NAMES.get(code, hex(code))}", 1)
    except XcpTimeoutError:
        fail(f"no answer from the ECU within {args.timeout:g} s (is the bench running, with "
             "this key?)", 1)
    except (RuntimeError, ValueError) as exc:
        fail(str(exc), 1)
    finally:
        close_bus(bus)
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        for k, v in doc.items():
            print(f"{k}: {v}")
    return 1 if doc.get("lost") else 0


def _info(args, key, a2l, bus, items) -> dict:
    with xt.connected(bus, key, timeout=args.timeout) as x:
        doc = xt.session(x, a2l)
        st = x.getStatus()
        doc.update(locked=[k for k in ("calpag", "daq") if st.resourceProtectionStatus[k]],
                   daq_running=bool(st.sessionStatus.daqRunning),
                   ecu_page=x.getCalPage(0x01, 0), xcp_page=x.getCalPage(0x02, 0),
                   a2l_name=x.identifier(1))
        x.disconnect()
    return doc


def _get(args, key, a2l, bus, items) -> dict:
    it = items[0]
    with xt.connected(bus, key, timeout=args.timeout) as x:
        xt.session(x, a2l)
        values = xt.read(x, it)
        x.disconnect()
    return {"name": it.name, "value": _show(it, values), "unit": it.unit}


def _show(it, values):
    if it.enum is not None:
        values = [it.enum[int(v)] if 0 <= v < len(it.enum) else v for v in values]
    return values[0] if len(values) == 1 else values


def _set(args, key, a2l, bus, items) -> dict:
    it = items[0]
    if not it.writable:
        raise ValueError(f"{it.name} is read-only in the A2L")
    data = xt.encode(it, args.value)
    with xt.connected(bus, key, timeout=args.timeout) as x:
        xt.session(x, a2l)
        old = xt.read(x, it)
        xt.push(x, it.address, data)
        new = xt.read(x, it)
        x.disconnect()
    return {"name": it.name, "old": _show(it, old), "new": _show(it, new), "unit": it.unit}


def _measure(args, key, a2l, bus, items) -> dict:
    from hil.apps.xcpdaq import measure

    if args.prescaler < 1 or not 0 < args.seconds <= 3600:
        raise ValueError("--prescaler must be >= 1 and --seconds in (0, 3600]")
    return measure(args, key, a2l, bus, items, EVENT_NAMES[args.event])


def _save(args, key, a2l, bus, items) -> dict:
    """Every writable CAL object whose working value differs from the reference page's, as
    the ``[calibration]`` table of a design file (``calib.calpage``), written whole or not at
    all (a temporary file renamed)."""
    import os

    from calib.calpage import design_text
    from calib.errors import ConfigError
    from calib.options import load_options
    from hil.xcp.memory import REFERENCE, WORKING
    from hil.xcp.protocol import PAGE_XCP

    if args.design is not None:                  # (a bad base: one line, before connecting)
        try:
            load_options(args.design)
        except ConfigError as exc:
            raise ValueError(f"--design: {exc}") from None

    cal = [it for n, it in sorted(a2l.items.items()) if n.startswith("cal.") and it.writable]
    raw = {}
    with xt.connected(bus, key, timeout=args.timeout) as x:
        xt.session(x, a2l)
        for page in (REFERENCE, WORKING):
            x.setCalPage(PAGE_XCP, 0, page)         # (the master's view)
            for it in cal:
                x.setMta(it.address)
                raw[page, it.name] = bytes(x.upload(it.size)[:it.size])
        x.disconnect()
    changed = {}
    for it in cal:
        if raw[REFERENCE, it.name] != raw[WORKING, it.name]:
            v = it.physical(raw[WORKING, it.name])
            if np.dtype(it.dtype).kind in "iu" and it.factor == 1.0:
                v = [int(e) for e in v]             # (an integer field stays whole)
            changed[it.name[len("cal."):]] = v[0] if it.count == 1 else v
    text = design_text(changed, args.design, header=(
        f"the working page of ECU {a2l.epk}, saved by python -m hil xcp save\n"
        f"(what differs from its reference page; read back with --design)"))
    tmp = Path(args.file).with_name(Path(args.file).name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, args.file)
    return {"file": args.file, "changed": sorted(changed), "objects": len(cal)}


_VERBS = {"info": _info, "get": _get, "set": _set, "measure": _measure, "save": _save}
