"""Bus load of the DBC's cyclic messages at a given bit rate (default 500 kbit/s).

    python -m tools.busload [--bitrate 500000] [--daq EVENT[/PRESCALER]:ODTS ...] [--json]

``--daq 1ms/4:2`` adds an XCP DAQ list of 2 ODTs on the 1 ms event every 4th sample (each
ODT one DTO, an 8-byte classic frame); with any ``--daq``, the verdict is the XCP slave's
budget (``hil.xcp.daq.BUDGET``): exit 1 over it.

Frame length of a classic CAN data frame with an 11-bit ID: 47 + 8 n bits, plus worst-case
bit stuffing floor((34 + 8 n - 1) / 4) over the stuffed part (SOF to CRC).
"""

from __future__ import annotations

import argparse

from hil.cli import add_json_argument, emit
from hil.transport.busload import cyclic, frame_bits
from hil.transport.codec import DBC_PATH, Codec


def daq_spec(text: str) -> tuple[str, int, int]:
    """EVENT[/PRESCALER]:ODTS as (event, prescaler, odts); ValueError with the reason."""
    from calib.a2l import EVENTS
    from hil.xcp.daq import MAX_PID

    names = {e[1]: e for e in EVENTS}
    try:
        head, odts = text.split(":")
        event, _, pre = head.partition("/")
        prescaler, n = int(pre or 1), int(odts)
    except ValueError:
        raise ValueError(f"--daq {text!r}: EVENT[/PRESCALER]:ODTS, e.g. 1ms/4:2") from None
    if event not in names or not 1 <= prescaler <= 255 or not 1 <= n <= MAX_PID:
        raise ValueError(f"--daq {text!r}: event one of {', '.join(names)}, prescaler "
                         f"1..255, ODTs 1..{MAX_PID}")
    return event, prescaler, n


def bus_load(bitrate: float = 500_000.0, daq: tuple = ()) -> dict:
    """The DBC's cyclic traffic, and the DAQ lists ``daq`` ((event, prescaler, odts), ...)."""
    from calib.a2l import EVENTS, MAX_DTO
    from hil.xcp.daq import list_bits_per_s

    codec = Codec()
    rows = cyclic(codec)
    channel = {short: (ch, ms) for _, short, ch, ms in EVENTS}
    for event, prescaler, odts in daq:
        ch, ms = channel[event]
        rows.append({"message": f"DAQ {event}/{prescaler} x{odts}",
                     "id": codec.message("XCP_RES").frame_id, "dlc": MAX_DTO,
                     "cycle_ms": ms * prescaler / odts, "bits_per_frame": frame_bits(MAX_DTO),
                     "bits_per_s": list_bits_per_s(odts, ch, prescaler)})
    for r in rows:
        r["load"] = r["bits_per_s"] / bitrate
    total = sum(r["bits_per_s"] for r in rows)
    out = {"dbc": str(DBC_PATH), "bitrate": bitrate, "messages": rows,
           "total_bits_per_s": total, "load": total / bitrate}
    if daq:
        from hil.xcp.daq import BUDGET

        out.update(budget=BUDGET, verdict="pass" if out["load"] <= BUDGET else "fail")
    return out


def _render(o: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"Bus load at {o['bitrate'] / 1000:g} kbit/s (worst-case stuffing)")
    for c in ("message", "id", "DLC", "cycle ms", "bits/frame", "load"):
        t.add_column(c, justify="right")
    for r in o["messages"]:
        t.add_row(r["message"], hex(r["id"]), str(r["dlc"]), f"{r['cycle_ms']:g}",
                  str(r["bits_per_frame"]), f"{r['load']:.1%}")
    t.add_row("total", "", "", "", "", f"{o['load']:.1%}")
    Console().print(t)
    if "verdict" in o:
        Console().print(f"DAQ budget {o['budget']:.0%}: {o['verdict']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.busload", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bitrate", type=float, default=500_000.0)
    parser.add_argument("--daq", action="append", default=[], metavar="EVENT[/PRE]:ODTS",
                        help="an XCP DAQ list to count (repeatable)")
    add_json_argument(parser)
    args = parser.parse_args(argv)
    if not args.bitrate > 0:
        parser.error(f"--bitrate must be positive, got {args.bitrate:g}")
    try:
        daq = tuple(daq_spec(d) for d in args.daq)
    except ValueError as exc:
        parser.error(str(exc))
    o = bus_load(args.bitrate, daq)
    emit(o, args.json, _render)
    return 1 if o.get("verdict") == "fail" else 0


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
