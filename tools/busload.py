"""Bus load of the DBC's cyclic messages at a given bit rate (default 500 kbit/s).

    python -m tools.busload [--bitrate 500000] [--json]

Frame length of a classic CAN data frame with an 11-bit ID: 47 + 8 n bits, plus worst-case
bit stuffing floor((34 + 8 n - 1) / 4) over the stuffed part (SOF to CRC).
"""

from __future__ import annotations

import argparse

from hil.cli import add_json_argument, emit
from hil.transport.busload import cyclic
from hil.transport.codec import DBC_PATH


def bus_load(bitrate: float = 500_000.0) -> dict:
    rows = cyclic()
    for r in rows:
        r["load"] = r["bits_per_s"] / bitrate
    total = sum(r["bits_per_s"] for r in rows)
    return {"dbc": str(DBC_PATH), "bitrate": bitrate, "messages": rows,
            "total_bits_per_s": total, "load": total / bitrate}


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.busload", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bitrate", type=float, default=500_000.0)
    add_json_argument(parser)
    args = parser.parse_args(argv)
    emit(bus_load(args.bitrate), args.json, _render)
    return 0


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
