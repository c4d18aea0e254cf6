"""The ECU's A2L (ASAM MCD-2 MC 1.71) from its memory image (``calib.image``): written by
``make tables`` as ``c/generated/ecu.a2l``, reproducibly (no date: the same inputs give the
same bytes).

What it holds: MOD_PAR with the EPK and one MEMORY_SEGMENT per image segment (CAL with a
reference and a working page); IF_DATA XCP (the protocol layer, dynamic DAQ with the 1 ms
and 10 ms events, XCP on CAN with the DBC's IDs); a COMPU_METHOD per fixed-point format and
decimal scaling (``physical = raw * factor``), the modes as a verbal table; CHARACTERISTICs
(VALUE, VAL_BLK with MATRIX_DIM, a CURVE over its AXIS_PTS) for CAL and FX, MEASUREMENTs for
the state, the inputs and the outputs, with units and limits. The XCP parameters the slave
(``hil.xcp``) implements are the constants here: the A2L and the slave cannot disagree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.image import DATATYPE, Image, Obj

# XCP as the slave implements it
XCP_VERSION = 0x0104           # protocol layer 1.4
XCP_CAN_VERSION = 0x0100
MAX_CTO = 8
MAX_DTO = 8
MAX_DAQ = 4                    # dynamic DAQ lists
MAX_ODT_ENTRY_SIZE = 7         # one entry fills at most an ODT's payload (MAX_DTO - PID)
TIMESTAMP_TICKS = 1            # 1 us per DAQ timestamp tick, 4 bytes, on the first ODT
# (name, short name, channel, cycle in ms): the ECU tick and every 10th tick
EVENTS = (("ECU tick 1 ms", "1ms", 0, 1), ("ECU tick 10 ms", "10ms", 1, 10))
TIMEOUTS_MS = (1000, 1000, 1000, 1000, 1000, 1000, 200)     # T1..T7
PAGES = ("reference", "working")                            # page 0, 1 of the CAL segment
OPTIONAL_CMDS = ("GET_COMM_MODE_INFO", "GET_ID", "GET_SEED", "UNLOCK", "SET_MTA", "UPLOAD",
                 "SHORT_UPLOAD", "DOWNLOAD", "DOWNLOAD_NEXT", "SHORT_DOWNLOAD", "SET_CAL_PAGE",
                 "GET_CAL_PAGE", "GET_PAG_PROCESSOR_INFO", "SET_DAQ_PTR", "WRITE_DAQ",
                 "SET_DAQ_LIST_MODE", "START_STOP_DAQ_LIST", "START_STOP_SYNCH", "GET_DAQ_CLOCK",
                 "GET_DAQ_PROCESSOR_INFO", "GET_DAQ_RESOLUTION_INFO", "GET_DAQ_EVENT_INFO",
                 "FREE_DAQ", "ALLOC_DAQ", "ALLOC_ODT", "ALLOC_ODT_ENTRY")
MAX_BS = 40                    # DOWNLOAD_NEXT frames of a block: 240 bytes, 30 doubles
_LAYOUT = {"f8": "RL_F64", "i8": "RL_I64", "i4": "RL_I32", "u1": "RL_U8"}


@dataclass(frozen=True)
class CanIds:
    master: int                # XCP_CMD: the master's CMD/STIM
    slave: int                 # XCP_RES: the slave's RES/ERR/EV/SERV/DAQ
    bitrate: int = 500_000


def _num(v: float) -> str:
    """A limit or coefficient as A2L text: the shortest repr that reads back equal."""
    if not np.isfinite(v):
        raise ValueError(f"non-finite number {v} in the A2L")
    v = float(v)
    return repr(int(v)) if v == int(v) and abs(v) < 2 ** 53 else repr(v)


def _cm_name(o: Obj) -> str:
    if o.enum is not None:
        return "CM_MODE"
    if o.frac is not None:
        return f"CM_Q{o.frac}" if o.frac >= 0 else f"CM_QM{-o.frac}"
    if o.factor is not None:
        return "CM_X" + repr(float(o.factor)).replace(".", "p").replace("-", "m")
    return "NO_COMPU_METHOD"


def _factor(o: Obj) -> float:
    return 2.0 ** -o.frac if o.frac is not None else o.factor


def _q(text: str) -> str:
    return '"' + text.replace('"', "'") + '"'


def compu_methods(objs) -> list[str]:
    out, seen = [], set()
    for o in objs:
        name = _cm_name(o)
        if name in seen or name == "NO_COMPU_METHOD":
            continue
        seen.add(name)
        if o.enum is not None:
            out.append(f'    /begin COMPU_METHOD {name} "mode" TAB_VERB "%12.0" ""\n'
                       f"      COMPU_TAB_REF VT_MODE\n    /end COMPU_METHOD")
            pairs = " ".join(f'{i} "{n}"' for i, n in enumerate(o.enum))
            out.append(f'    /begin COMPU_VTAB VT_MODE "" TAB_VERB {len(o.enum)} {pairs}\n'
                       f"    /end COMPU_VTAB")
            continue
        what = f"Q{o.frac}: raw * 2^-{o.frac}" if o.frac is not None else f"raw * {o.factor:g}"
        out.append(f'    /begin COMPU_METHOD {name} "{what}" LINEAR "%16.9" ""\n'
                   f"      COEFFS_LINEAR {_num(_factor(o))} 0\n    /end COMPU_METHOD")
    return out


def _matrix(o: Obj) -> str:
    return f"      MATRIX_DIM {' '.join(str(n) for n in o.shape)}\n" if o.shape else ""


def characteristic(o: Obj, image: Image) -> str:
    rw = "" if o.writable else "      READ_ONLY\n"
    unit = f"      PHYS_UNIT {_q(o.unit)}\n" if o.unit else ""
    head = (f"{o.name} {_q(o.text)}")
    if o.axis is not None:
        ax = image.objects[o.axis]
        return (f"    /begin CHARACTERISTIC {head} CURVE 0x{o.address:X} {_LAYOUT[o.dtype]} 0 "
                f"{_cm_name(o)} {_num(o.lower)} {_num(o.upper)}\n"
                f"      /begin AXIS_DESCR COM_AXIS NO_INPUT_QUANTITY NO_COMPU_METHOD "
                f"{ax.shape[0]} {_num(ax.lower)} {_num(ax.upper)}\n"
                f"        AXIS_PTS_REF {ax.name}\n      /end AXIS_DESCR\n"
                f"{rw}{unit}    /end CHARACTERISTIC")
    kind = "VAL_BLK" if o.shape else "VALUE"
    return (f"    /begin CHARACTERISTIC {head} {kind} 0x{o.address:X} {_LAYOUT[o.dtype]} 0 "
            f"{_cm_name(o)} {_num(o.lower)} {_num(o.upper)}\n"
            f"{_matrix(o)}{rw}{unit}    /end CHARACTERISTIC")


def axis_pts(o: Obj) -> str:
    return (f"    /begin AXIS_PTS {o.name} {_q(o.text)} 0x{o.address:X} NO_INPUT_QUANTITY "
            f"RL_AXIS_{o.dtype.upper()} 0 {_cm_name(o)} {o.shape[0]} "
            f"{_num(o.lower)} {_num(o.upper)}\n"
            f"{'' if o.writable else '      READ_ONLY' + chr(10)}    /end AXIS_PTS")


def measurement(o: Obj) -> str:
    unit = f"      PHYS_UNIT {_q(o.unit)}\n" if o.unit else ""
    return (f"    /begin MEASUREMENT {o.name} {_q(o.text)} {DATATYPE[o.dtype]} {_cm_name(o)} "
            f"0 0 {_num(o.lower)} {_num(o.upper)}\n"
            f"      ECU_ADDRESS 0x{o.address:X}\n{_matrix(o)}{unit}    /end MEASUREMENT")


def _if_data_xcp(ids: CanIds) -> str:
    t = " ".join(str(v) for v in TIMEOUTS_MS)
    cmds = "\n".join(f"        OPTIONAL_CMD {c}" for c in OPTIONAL_CMDS)
    events = "\n".join(
        f'        /begin EVENT "{name}" "{short}" {ch} DAQ 0xFF {ms} 6 0\n        /end EVENT'
        for name, short, ch, ms in EVENTS)
    return f"""    /begin IF_DATA XCP
      /begin PROTOCOL_LAYER 0x{XCP_VERSION:04X} {t} {MAX_CTO} {MAX_DTO}
        BYTE_ORDER_MSB_LAST ADDRESS_GRANULARITY_BYTE
{cmds}
        /begin COMMUNICATION_MODE_SUPPORTED BLOCK SLAVE MASTER {MAX_BS} 0
        /end COMMUNICATION_MODE_SUPPORTED
      /end PROTOCOL_LAYER
      /begin DAQ DYNAMIC {MAX_DAQ} {len(EVENTS)} 0 OPTIMISATION_TYPE_DEFAULT
        ADDRESS_EXTENSION_FREE IDENTIFICATION_FIELD_TYPE_ABSOLUTE
        GRANULARITY_ODT_ENTRY_SIZE_DAQ_BYTE {MAX_ODT_ENTRY_SIZE} OVERLOAD_INDICATION_PID
        PRESCALER_SUPPORTED
        /begin TIMESTAMP_SUPPORTED {TIMESTAMP_TICKS} SIZE_DWORD UNIT_1US TIMESTAMP_FIXED
        /end TIMESTAMP_SUPPORTED
{events}
      /end DAQ
      /begin PAG 1
      /end PAG
      /begin XCP_ON_CAN 0x{XCP_CAN_VERSION:04X}
        CAN_ID_MASTER 0x{ids.master:X}
        CAN_ID_SLAVE 0x{ids.slave:X}
        BAUDRATE {ids.bitrate}
        MAX_DLC_REQUIRED
      /end XCP_ON_CAN
    /end IF_DATA"""


def _segment(seg, number: int | None) -> str:
    kind, mem = {"IDENT": ("DATA", "FLASH"), "CAL": ("DATA", "FLASH"),
                 "FX": ("DATA", "FLASH")}.get(seg.name, ("VARIABLES", "RAM"))
    xcp = ""
    if number is not None:
        pages = "\n".join(
            f"            /begin PAGE {i} ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE "
            f"{'XCP_WRITE_ACCESS_NOT_ALLOWED' if i == 0 else 'XCP_WRITE_ACCESS_DONT_CARE'}"
            f"\n            /end PAGE" for i in range(len(PAGES)))
        xcp = (f"\n        /begin IF_DATA XCP\n          /begin SEGMENT {number} {len(PAGES)} 0 0 0"
               f"\n{pages}\n          /end SEGMENT\n        /end IF_DATA")
    return (f'      /begin MEMORY_SEGMENT {seg.name} "{seg.record}" {kind} {mem} INTERN '
            f"0x{seg.base:X} {seg.size} -1 -1 -1 -1 -1{xcp}\n      /end MEMORY_SEGMENT")


def generate(image: Image, ids: CanIds, generator: str, digest: str) -> str:
    objs = list(image.objects.values())
    axes = {o.axis for o in objs if o.axis}
    segs = "\n".join(_segment(s, 0 if s.name == "CAL" else None) for s in image.segments)
    layouts = "\n".join(
        f"    /begin RECORD_LAYOUT {name} FNC_VALUES 1 {DATATYPE[k]} ROW_DIR DIRECT\n"
        f"    /end RECORD_LAYOUT\n"
        f"    /begin RECORD_LAYOUT RL_AXIS_{k.upper()} AXIS_PTS_X 1 {DATATYPE[k]} INDEX_INCR "
        f"DIRECT\n    /end RECORD_LAYOUT" for k, name in _LAYOUT.items())
    body = [f"/* Generated by {generator}: do not edit. Inputs SHA-256: {digest} */",
            "ASAP2_VERSION 1 71",
            '/begin PROJECT SUSPENSION "Intelligent active-suspension ECU"',
            f'  /begin HEADER "memory image of calib/image.py"\n    VERSION "{image.epk}"'
            "\n  /end HEADER",
            '  /begin MODULE SUSPENSION_ECU "the ECU node (XCP on CAN slave)"',
            f'    /begin MOD_PAR "little-endian, packed records"\n      VERSION "{image.epk}"'
            f"\n      ADDR_EPK 0x{image.segment('IDENT').base:X}\n      EPK \"{image.epk}\"",
            segs, "    /end MOD_PAR",
            '    /begin MOD_COMMON "" BYTE_ORDER MSB_LAST ALIGNMENT_BYTE 1 ALIGNMENT_WORD 1\n'
            "      ALIGNMENT_LONG 1 ALIGNMENT_INT64 1 ALIGNMENT_FLOAT32_IEEE 1 "
            "ALIGNMENT_FLOAT64_IEEE 1\n    /end MOD_COMMON",
            _if_data_xcp(ids), layouts]
    body += compu_methods(objs)
    body += [axis_pts(o) if o.name in axes else characteristic(o, image)
             for o in objs if o.characteristic]
    body += [measurement(o) for o in objs if not o.characteristic]
    body += ["  /end MODULE", "/end PROJECT", ""]
    return "\n".join(body)


A2L = "ecu.a2l"


def files(image: Image, ids: CanIds, generator: str, digest: str) -> dict[str, str]:
    """{file name: text}: the A2L and the image as C (``calib.image_c``)."""
    from calib import image_c

    top = (f"/* Generated by {generator}: do not edit.\n * Inputs SHA-256: {digest}\n"
           " * The ECU's memory image (calib/image.py), as ecu.a2l describes it. */")
    out = {A2L: generate(image, ids, generator, digest)}
    out.update(image_c.generate(image, top))
    return out
