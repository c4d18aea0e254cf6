"""C-portable coefficient tables (``calib.c_tables``): everything the firmware needs, as a C99
header and source.

    python -m tools.tables [--out DIR] [--vehicle FILE] [--gains FILE] [--design FILE] [--check] [--json]

writes DIR/ecu_tables.h and DIR/ecu_tables.c (default DIR: c/generated), and the ECU's memory
image: its A2L (DIR/ecu.a2l, ``calib.a2l``) and the image as C (ecu_image.h/.c/.ld,
``calib.image_c``). ``--check`` writes nothing and exits 1 when the files in DIR differ from
what would be generated.
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

from calib import a2l
from calib.c_tables import GENERATOR, build, generate, inputs_digest
from calib.image import Image
from hil.cli import (add_design_argument, add_json_argument, add_vehicle_argument, design_or_exit,
                     emit, fail, vehicle_or_exit)
from hil.config import ConfigError
from hil.transport.codec import Codec
from calib.options import DesignOptions

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "c" / "generated"


def xcp_ids() -> a2l.CanIds:
    """XCP on CAN's identifiers, from the DBC."""
    codec = Codec()
    return a2l.CanIds(codec.message("XCP_CMD").frame_id, codec.message("XCP_RES").frame_id)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.tables", description=__doc__.split("\n")[0])
    ap.add_argument("--out", metavar="DIR", default=str(DEFAULT_OUT),
                    help="where to write ecu_tables.h/.c (default: c/generated)")
    add_vehicle_argument(ap)
    ap.add_argument("--gains", metavar="FILE", help="GA-LQR gains file (default: the shipped one)")
    add_design_argument(ap)
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if the files in DIR differ from the generated ones")
    add_json_argument(ap)
    args = ap.parse_args(argv)
    cfg = vehicle_or_exit(args.vehicle)
    opts = design_or_exit(args.design)
    gains = Path(args.gains) if args.gains else None
    try:
        p = build(cfg, opts, gains)
        files = generate(cfg, gains, opts, params=p)
        files.update(a2l.files(Image(p), xcp_ids(), GENERATOR,
                               inputs_digest(cfg, gains, opts or DesignOptions())))
    except ConfigError as exc:
        fail(str(exc))
    out = Path(args.out)
    result = {"out": str(out), "files": {}, "differs": []}
    for name, text in files.items():
        path = out / name
        data = text.encode()
        result["files"][name] = hashlib.sha256(data).hexdigest()
        old = path.read_bytes() if path.is_file() else None
        if old != data:
            result["differs"].append(name)
            if not args.check:
                out.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)

    def render(r):
        verb = "differs from the generator" if args.check else "written"
        for name, sha in r["files"].items():
            state = verb if name in r["differs"] else "unchanged"
            print(f"{out / name}: {state} (sha256 {sha[:16]}...)")

    emit(result, args.json, render)
    return 1 if args.check and result["differs"] else 0


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
