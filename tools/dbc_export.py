"""The DBC in the formats other tools open: AUTOSAR ARXML 4, KCD and PEAK SYM, written with
canmatrix and each loaded back and checked signal by signal against the DBC.

    python -m tools.dbc_export [--formats arxml,kcd,sym] [--out DIR]    (default: out/dbc)

canmatrix's own ``canconvert`` exits 0 when a format could not be written; this command
exits 1, with one line per problem, when a file is missing, does not load, or a signal's
layout (start bit, length, byte order, sign), scale, offset, range, unit or value table
differs from the DBC's. ARXML gives every I-SIGNAL its own path, so a signal name that
repeats across messages (COUNTER, CHECKSUM, ...) is written as ``<MESSAGE>_<SIGNAL>`` there.
Loaded back with cantools (ARXML, KCD) or canmatrix (SYM: cantools reads only SYM 6.0,
canmatrix writes 5.0).
"""

from __future__ import annotations

import argparse
import copy
import sys
from collections import Counter
from pathlib import Path

FORMATS = ("arxml", "kcd", "sym")


def unique_signal_names(matrix) -> dict[tuple[str, str], str]:
    """Rename, in ``matrix`` (canmatrix), every signal whose name is not unique across
    messages to ``<MESSAGE>_<SIGNAL>``; returns (message, DBC name) -> exported name."""
    counts = Counter(s.name for f in matrix.frames for s in f.signals)
    names = {}
    for f in matrix.frames:
        for s in f.signals:
            new = f"{f.name}_{s.name}" if counts[s.name] > 1 else s.name
            names[(f.name, s.name)] = new
            s.name = new
    return names


def export(out: Path, formats=FORMATS, dbc: Path | None = None) -> dict[str, Path]:
    """Write each format into ``out``; returns format -> path."""
    import canmatrix.formats

    from hil.transport.codec import DBC_PATH

    dbc = Path(dbc or DBC_PATH)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for fmt in formats:
        matrices = canmatrix.formats.loadp(str(dbc))
        if fmt == "arxml":
            matrices = {k: copy.deepcopy(m) for k, m in matrices.items()}
            for m in matrices.values():
                unique_signal_names(m)
        path = out / f"{dbc.stem}.{fmt}"
        path.unlink(missing_ok=True)
        canmatrix.formats.dumpp(matrices, str(path))
        if fmt in FIXES:
            FIXES[fmt](path, dbc)
        paths[fmt] = path
    return paths


# canmatrix 1.2's writers, mended where the file they write is not what the DBC says or
# what the format's schema asks for (each found by ``check`` below):
def _fix_kcd(path: Path, dbc: Path) -> None:
    """KCD: canmatrix writes slope and intercept with six significant digits (``%g``: the
    duty's 2^-15 became 3.05176e-05); written here exact, from the DBC."""
    import lxml.etree

    ref = _reference(dbc)
    tree = lxml.etree.parse(str(path))
    ns = {"k": tree.getroot().nsmap[None]}
    for msg in tree.iterfind(".//k:Message", ns):
        m = ref.get_message_by_frame_id(int(msg.get("id"), 0))
        for sig in msg.iterfind("k:Signal", ns):
            s = m.get_signal_by_name(sig.get("name"))
            value = sig.find("k:Value", ns)
            for attr, number, default in (("slope", s.scale, 1), ("intercept", s.offset, 0)):
                if value is not None and float(number) != default:
                    value.set(attr, repr(float(number)))
    tree.write(str(path), xml_declaration=True, encoding="UTF-8", pretty_print=True)


def _fix_arxml(path: Path, dbc: Path) -> None:
    """ARXML: canmatrix gives a signal's compu method (scale, offset, value table) and unit
    only in its I-SIGNAL's network representation; AUTOSAR 4 also has them in the
    SYSTEM-SIGNAL's physical props, where cantools reads them: copied there. And canmatrix
    writes a SW-BASE-TYPE's BASE-TYPE-ENCODING only for floats; AUTOSAR names the integers'
    too (2C: two's complement, NONE: unsigned), and cantools requires it."""
    import lxml.etree

    tree = lxml.etree.parse(str(path))
    ns = tree.getroot().nsmap[None]

    def q(tag):
        return f"{{{ns}}}{tag}"

    systems = {el.find(q("SHORT-NAME")).text: el for el in tree.iter(q("SYSTEM-SIGNAL"))}
    for isig in tree.iter(q("I-SIGNAL")):
        ref = isig.find(q("SYSTEM-SIGNAL-REF"))
        props = isig.find(f"{q('NETWORK-REPRESENTATION-PROPS')}/{q('SW-DATA-DEF-PROPS-VARIANTS')}")
        system = systems.get(ref.text.rsplit("/", 1)[-1]) if ref is not None else None
        if props is None or system is None or system.find(q("PHYSICAL-PROPS")) is not None:
            continue
        physical = lxml.etree.SubElement(system, q("PHYSICAL-PROPS"))
        variants = lxml.etree.SubElement(physical, q("SW-DATA-DEF-PROPS-VARIANTS"))
        for cond in props.iter(q("SW-DATA-DEF-PROPS-CONDITIONAL")):
            new = lxml.etree.SubElement(variants, q("SW-DATA-DEF-PROPS-CONDITIONAL"))
            for tag in ("COMPU-METHOD-REF", "UNIT-REF"):
                for el in cond.iter(q(tag)):
                    new.append(copy.deepcopy(el))
    # the compu methods, rewritten from the DBC: canmatrix writes them without CATEGORY
    # (cantools then reads no scaling at all), without limits (no range) and with the
    # factor in six digits
    import canmatrix.formats

    ref = _reference(dbc)
    exported = unique_signal_names(canmatrix.formats.loadp_flat(str(dbc)))
    by_name = {new: ref.get_message_by_name(m).get_signal_by_name(sig)
               for (m, sig), new in exported.items()}
    for cm in tree.iter(q("COMPU-METHOD")):
        sig = by_name.get(cm.find(q("SHORT-NAME")).text)
        if sig is not None:
            _compu_method(cm, sig, q)
    for bt in tree.iter(f"{{{ns}}}SW-BASE-TYPE"):
        if bt.find(f"{{{ns}}}BASE-TYPE-ENCODING") is None:
            name = bt.find(f"{{{ns}}}SHORT-NAME").text
            enc = lxml.etree.SubElement(bt, f"{{{ns}}}BASE-TYPE-ENCODING")
            enc.text = "2C" if name.startswith("sint") else "NONE"
    tree.write(str(path), xml_declaration=True, encoding="UTF-8", pretty_print=True)


def _compu_method(cm, sig, q) -> None:
    """A COMPU-METHOD as AUTOSAR 4 has it for a DBC signal: LINEAR over its declared raw
    range, with its value table SCALE_LINEAR_AND_TEXTTABLE."""
    import lxml.etree

    for child in list(cm):
        if child.tag in (q("CATEGORY"), q("COMPU-INTERNAL-TO-PHYS")):
            cm.remove(child)
    at = 1 + (cm.find(q("DESC")) is not None)
    category = lxml.etree.Element(q("CATEGORY"))
    category.text = "SCALE_LINEAR_AND_TEXTTABLE" if sig.choices else "LINEAR"
    cm.insert(at, category)
    to_phys = lxml.etree.SubElement(cm, q("COMPU-INTERNAL-TO-PHYS"))
    scales = lxml.etree.SubElement(to_phys, q("COMPU-SCALES"))

    def scale(lo, hi):
        el = lxml.etree.SubElement(scales, q("COMPU-SCALE"))
        for tag, value in (("LOWER-LIMIT", lo), ("UPPER-LIMIT", hi)):
            lxml.etree.SubElement(el, q(tag)).text = str(value)
        return el

    for value, name in sorted((sig.choices or {}).items()):
        const = lxml.etree.SubElement(scale(int(value), int(value)), q("COMPU-CONST"))
        lxml.etree.SubElement(const, q("VT")).text = str(name)
    from hil.transport.codec import declared_raw_range

    lo, hi = declared_raw_range(sig)
    coeffs = lxml.etree.SubElement(scale(lo, hi), q("COMPU-RATIONAL-COEFFS"))
    num = lxml.etree.SubElement(coeffs, q("COMPU-NUMERATOR"))
    lxml.etree.SubElement(num, q("V")).text = repr(float(sig.offset))
    lxml.etree.SubElement(num, q("V")).text = repr(float(sig.scale))
    den = lxml.etree.SubElement(coeffs, q("COMPU-DENOMINATOR"))
    lxml.etree.SubElement(den, q("V")).text = "1"


FIXES = {"kcd": _fix_kcd, "arxml": _fix_arxml}


def _reference(dbc: Path):
    import cantools

    return cantools.database.load_file(str(dbc))


def check(fmt: str, path: Path, dbc: Path | None = None) -> list[str]:
    """The differences between an exported file, loaded back, and the DBC (empty: none)."""
    from hil.transport.codec import DBC_PATH

    dbc = Path(dbc or DBC_PATH)
    ref = _reference(dbc)
    if not path.is_file() or path.stat().st_size == 0:
        return [f"{path}: not written"]
    try:
        got = _load(fmt, path)
    except Exception as exc:  # noqa: BLE001 - the loader's own error, reported in one line
        return [f"{path}: does not load: {type(exc).__name__}: {exc}"]
    problems = []
    renamed = {}
    if fmt == "arxml":
        import canmatrix.formats

        renamed = unique_signal_names(copy.deepcopy(canmatrix.formats.loadp_flat(str(dbc))))
    for m in ref.messages:
        # (canmatrix names an ARXML CAN-FRAME FRAME_<message>)
        g = got.get(m.name if fmt != "arxml" else f"FRAME_{m.name}")
        if g is None:
            problems.append(f"{path.name}: message {m.name} missing")
            continue
        if g["frame_id"] != m.frame_id or g["length"] != m.length:
            problems.append(f"{path.name}: {m.name}: ID/length {g['frame_id']:#x}/"
                            f"{g['length']} against {m.frame_id:#x}/{m.length}")
        for s in m.signals:
            name = renamed.get((m.name, s.name), s.name)
            gs = g["signals"].get(name)
            if gs is None:
                problems.append(f"{path.name}: {m.name}.{name} missing")
                continue
            want = _describe(s.start, s.length, s.byte_order, s.is_signed, s.scale, s.offset,
                             s.minimum, s.maximum, s.unit, s.choices)
            for key, value in want.items():
                if gs[key] != value:
                    problems.append(f"{path.name}: {m.name}.{name}: {key} {gs[key]!r} "
                                    f"against the DBC's {value!r}")
    return problems


def _describe(start, length, byte_order, signed, scale, offset, lo, hi, unit, choices) -> dict:
    return {"start": int(start), "length": int(length), "byte_order": byte_order,
            "signed": bool(signed), "scale": float(scale), "offset": float(offset),
            "minimum": None if lo is None else float(lo),
            "maximum": None if hi is None else float(hi), "unit": unit or "",
            "choices": {int(k): str(v) for k, v in (choices or {}).items()}}


def _load(fmt: str, path: Path) -> dict:
    """message name -> {frame_id, length, signals: name -> _describe(...)}."""
    if fmt in ("arxml", "kcd"):
        import cantools

        db = cantools.database.load_file(str(path))
        # (KCD: an absent min is 0 and max is 1, the schema's defaults; cantools says None)
        lo, hi = (0.0, 1.0) if fmt == "kcd" else (None, None)
        return {m.name: {"frame_id": m.frame_id, "length": m.length, "signals": {
            s.name: _describe(s.start, s.length, s.byte_order, s.is_signed, s.scale, s.offset,
                              lo if s.minimum is None else s.minimum,
                              hi if s.maximum is None else s.maximum, s.unit, s.choices)
            for s in m.signals}} for m in db.messages}
    import canmatrix.formats

    cm = canmatrix.formats.loadp_flat(str(path))
    out = {}
    for f in cm.frames:
        sigs = {}
        for s in f.signals:
            order = "little_endian" if s.is_little_endian else "big_endian"
            sigs[s.name] = _describe(s.get_startbit(bit_numbering=1, start_little=True),
                                     s.size, order, s.is_signed, s.factor, s.offset, s.min,
                                     s.max, s.unit, s.values)
        out[f.name] = {"frame_id": f.arbitration_id.id, "length": f.size, "signals": sigs}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.dbc_export", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--formats", default=",".join(FORMATS),
                   help=f"comma-separated, of {', '.join(FORMATS)} (default: all)")
    p.add_argument("--out", default="out/dbc", metavar="DIR")
    args = p.parse_args(argv)
    formats = [f.strip().lower() for f in args.formats.split(",") if f.strip()]
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        print(f"error: --formats: one or more of {', '.join(FORMATS)}, not {bad or 'none'}",
              file=sys.stderr)
        return 2
    try:
        paths = export(Path(args.out), formats)
    except Exception as exc:  # noqa: BLE001 - canmatrix's own error, in one line
        print(f"error: export failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    problems = []
    for fmt, path in paths.items():
        found = check(fmt, path)
        problems += found
        print(f"{fmt}: {path} " + ("checked: every message and signal as in the DBC"
                                   if not found else f"{len(found)} problem(s)"))
    for line in problems:
        print(f"error: {line}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
