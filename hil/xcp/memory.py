"""The memory an XCP master addresses: the image of ``calib.image`` over the ECU's live
records, and the calibration's working page with its checks.

Reads: IDENT is the EPK; CAL is the page the master selected (0: the reference, as the ECU
was built; 1: the working page); FX, STATE, INPUTS and OUTPUTS are the live records; a small
text area (``TEXT_BASE``) holds what GET_ID and GET_DAQ_EVENT_INFO point the master at.

Writes go to the working page only, and only to ``calib.calpage.WRITABLE`` objects, each
element whole (a transfer may end inside an element: its bytes wait for the next transfer,
which must continue at that address), each object changed passing the checks a design
file's value passes (``calib.calpage.refusal``: finite, inside its A2L limits, a gain row
only if its closed loop on the ECU's own model is stable). An accepted write gives new
parameters (``EcuParams``, derived fields and the fixed-point tables made again from them):
the ECU takes them between two ticks.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import numpy as np

from calib.calpage import refusal, replace_path, value_of
from calib.fx_tables import build_tables, pinned
from calib.image import Image, Obj
from firmware.fx.tables import FxTables
from firmware.layout import params_record
from firmware.params import EcuParams
from hil.xcp.protocol import (ERR_ACCESS_DENIED, ERR_OUT_OF_RANGE, ERR_PAGE_NOT_VALID,
                              ERR_SEQUENCE, ERR_WRITE_PROTECTED, XcpError)

TEXT_BASE = 0xFF000000
REFERENCE, WORKING = 0, 1


@dataclasses.dataclass
class Change:
    """An accepted write: the new parameters, their record, and the objects it changed (old,
    new values)."""

    params: EcuParams
    record: np.ndarray                  # params_record(params): the working page now
    objects: dict                       # name -> (old, new): lists of numbers
    tables: FxTables                    # the fixed-point tables, in the image's formats


class Memory:
    """``records()`` gives the live ``{"T", "S", "I", "O"}`` arrays (the ECU may make new
    ones: a reset makes a new state); the CAL pages are kept here: the reference as built
    (``image.P``), the working page as its parameters and their record."""

    def __init__(self, image: Image, records: Callable[[], dict]):
        self.image, self.records = image, records
        self.params, self.working, self.tables = image.params, image.P, image.tables
        self.text = bytearray()
        self.texts: dict[str, int] = {}
        # (address, bytes) of an element a transfer began and did not finish
        self.pending: Optional[tuple[int, bytearray]] = None
        self._cal = sorted((o for o in image.objects.values() if o.segment == "CAL"),
                           key=lambda o: o.address)
        self._epk = image.epk.encode().ljust(image.segment("IDENT").size, b"\0")

    def text_address(self, text: str) -> int:
        """Where ``text`` lies in the text area (added on first use)."""
        if text not in self.texts:
            self.texts[text] = TEXT_BASE + len(self.text)
            self.text += text.encode()
        return self.texts[text]

    def _segment(self, address: int, size: int):
        seg = self.image.find(address, size)
        if seg is None:
            raise XcpError(ERR_ACCESS_DENIED, f"0x{address:X}+{size} is outside the image")
        return seg

    def read(self, address: int, size: int, page: int) -> bytes:
        if TEXT_BASE <= address and address + size <= TEXT_BASE + len(self.text):
            return bytes(self.text[address - TEXT_BASE:address - TEXT_BASE + size])
        record, offset = self.readable(address, size)
        return self.sample(record, offset, size, page)

    def readable(self, address: int, size: int) -> tuple[str, int]:
        """(record, offset) of a readable range (a DAQ entry), or XcpError."""
        seg = self._segment(address, size)
        return seg.record, address - seg.base

    def sample(self, record: str, offset: int, size: int, page: int = WORKING) -> bytes:
        """``size`` bytes at ``offset`` of ``record`` (CAL: of ``page``)."""
        if record == "EPK":
            return self._epk[offset:offset + size]
        if record == "P":
            rec = self.image.P if page == REFERENCE else self.working
        else:
            rec = self.records()[record]
        return rec.view(np.uint8)[offset:offset + size].tobytes()

    # ---------------------------------------------------------------- writing
    def write(self, address: int, data: bytes, page: int) -> Optional[Change]:
        """Check and stage a transfer; the whole elements it completes become a Change
        (None: all of it waits inside one element). Refusals raise XcpError; a refused
        transfer leaves the page as it was and drops what waited."""
        pending, self.pending = self.pending, None
        if pending is not None:
            start, buf = pending
            if address != start + len(buf):
                raise XcpError(ERR_SEQUENCE, f"0x{address:X}: an element begun at 0x"
                                             f"{start:X} was not finished")
            buf = buf + data
        else:
            start, buf = address, bytearray(data)
        if page != WORKING:
            raise XcpError(ERR_WRITE_PROTECTED, "the reference page is read-only")
        if self.image.find(start, len(buf)) is not self.image.segment("CAL"):
            raise XcpError(ERR_WRITE_PROTECTED, f"0x{start:X}+{len(buf)}: not calibration")
        end = start + len(buf)
        objs = [o for o in self._cal if o.address < end and start < o.address + o.size]
        for o in objs:
            if not o.writable:
                raise XcpError(ERR_WRITE_PROTECTED, f"{o.name} is read-only")
        first, last = objs[0], objs[-1]
        isz = np.dtype(first.dtype).itemsize
        if (start - first.address) % isz:
            raise XcpError(ERR_OUT_OF_RANGE, f"0x{start:X} is inside an element of "
                                             f"{first.name}")
        isz = np.dtype(last.dtype).itemsize
        cut = last.address + (end - last.address) // isz * isz
        if cut <= start:                # (all of it inside one element: it waits)
            self.pending = (start, buf)
            return None
        if cut < end:                   # the whole elements now; the split one waits
            self.pending = (cut, bytearray(buf[cut - start:]))
            buf = buf[:cut - start]
            objs = [o for o in objs if o.address < cut]
        try:
            return self._apply(start, bytes(buf), objs)
        except XcpError:
            self.pending = None
            raise

    def _apply(self, start: int, data: bytes, objs: list[Obj]) -> Change:
        base = self.image.segment("CAL").base
        page = bytearray(self.working.tobytes())
        page[start - base:start - base + len(data)] = data
        p, changed = self.params, {}
        for o in objs:
            off = o.address - base
            new = np.frombuffer(bytes(page[off:off + o.size]), dtype=o.dtype)
            why = refusal(self.image.params, ".".join(o.path), new)
            if why:
                raise XcpError(ERR_OUT_OF_RANGE, why)
            old = np.ravel(np.asarray(value_of(p, o.path), dtype=float)).tolist()
            p = replace_path(p, o.path, new.reshape(o.shape) if o.shape else new[0])
            changed[o.name] = (old, new.astype(float).tolist())
        try:                    # (the C path's formats are fixed: the A2L states them)
            tables = pinned(build_tables(p), self.image.tables)
        except ValueError as exc:
            raise XcpError(ERR_OUT_OF_RANGE, str(exc)) from None
        self.params, self.working, self.tables = p, params_record(p), tables
        return Change(p, self.working, changed, tables)

    def page_valid(self, page: int) -> None:
        if page not in (REFERENCE, WORKING):
            raise XcpError(ERR_PAGE_NOT_VALID, f"page {page}")
