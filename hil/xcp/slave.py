"""The XCP slave's command processor: one CTO in, its RES or ERR packets out (byte strings,
not yet padded), between two ticks; never inside one.

Calibration and DAQ are locked after CONNECT until GET_SEED/UNLOCK with the key of the run's
secret: key = HMAC-SHA256(secret, "hil.xcp key" + seed)[:6] (``key_of``); a wrong key is
ERR_ACCESS_LOCKED and ends the session, as the standard says. Commands before CONNECT get
no answer. An accepted DOWNLOAD is a ``memory.Change`` the node applies at the next tick
boundary (``take_changes``); the ECU page (SET_CAL_PAGE) likewise.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
from typing import Optional

from calib.a2l import (EVENTS, MAX_BS, MAX_CTO, MAX_DAQ, MAX_DTO, MAX_ODT_ENTRY_SIZE,
                       TIMESTAMP_TICKS, XCP_CAN_VERSION, XCP_VERSION)
from hil.xcp import protocol as x
from hil.xcp.daq import Daq
from hil.xcp.memory import WORKING, Change, Memory
from hil.xcp.protocol import XcpError

SEED_LEN = KEY_LEN = 6
LOCKABLE = x.RES_CAL_PAG | x.RES_DAQ
_DAQ_CMDS = {x.FREE_DAQ, x.ALLOC_DAQ, x.ALLOC_ODT, x.ALLOC_ODT_ENTRY, x.SET_DAQ_PTR,
             x.WRITE_DAQ, x.SET_DAQ_LIST_MODE, x.START_STOP_DAQ_LIST, x.START_STOP_SYNCH}
_CAL_CMDS = {x.DOWNLOAD, x.DOWNLOAD_NEXT, x.SHORT_DOWNLOAD, x.SET_CAL_PAGE}


def key_of(secret: bytes, seed: bytes) -> bytes:
    return hmac.new(secret, b"hil.xcp key" + bytes(seed), hashlib.sha256).digest()[:KEY_LEN]


class Slave:
    def __init__(self, memory: Memory, daq: Daq, secret: bytes, tick=lambda: 0):
        if not secret:
            raise ValueError("the XCP slave needs the run's secret (its seed and key)")
        self.memory, self.daq, self.secret, self.tick = memory, daq, secret, tick
        self.connected = False
        self.protection = LOCKABLE
        self.mta = 0
        self.xcp_page, self.ecu_page = WORKING, WORKING
        self.seed: Optional[bytes] = None
        self._seed_for = 0                 # the resource the seed unlocks
        self.seeds = 0
        self.block: Optional[tuple[int, bytearray]] = None   # DOWNLOAD block: (left, data)
        self.refused_left = 0              # bytes still to come of a refused DOWNLOAD block
        self.changes: list[Change] = []
        self.page_change = False           # the ECU page changed: the node swaps records
        self.requests = self.errors = 0
        self.refusals: dict[str, int] = {}

    # ---------------------------------------------------------------- entry point
    def handle(self, cto: bytes) -> list[bytes]:
        if not cto:
            return []
        cmd = cto[0]
        if not self.connected and cmd != x.CONNECT:
            return []                       # (a slave not connected answers nothing)
        if self.refused_left:
            # the rest of a block whose DOWNLOAD was refused: its one ERR is sent (a master
            # in block mode reads no answer before the block's end, so one per frame would
            # answer its next commands)
            if cmd == x.DOWNLOAD_NEXT and cto[1:2] == bytes([self.refused_left]):
                self.refused_left = max(0, self.refused_left - (MAX_CTO - 2))
                return []
            self.refused_left = 0
        self.requests += 1
        try:
            if cmd in _DAQ_CMDS and self.protection & x.RES_DAQ:
                raise XcpError(x.ERR_ACCESS_LOCKED, "DAQ is locked: GET_SEED/UNLOCK first")
            if cmd in _CAL_CMDS and self.protection & x.RES_CAL_PAG:
                raise XcpError(x.ERR_ACCESS_LOCKED, "calibration is locked: unlock first")
            if cmd != x.DOWNLOAD_NEXT and self.block is not None:
                self.block = None
                raise XcpError(x.ERR_SEQUENCE, "a DOWNLOAD block was not finished")
            handler = _HANDLERS.get(cmd)
            if handler is None:
                raise XcpError(x.ERR_CMD_UNKNOWN, f"command 0x{cmd:02X}")
            try:
                return handler(self, cto)
            except (struct.error, IndexError):
                raise XcpError(x.ERR_CMD_SYNTAX, f"command 0x{cmd:02X} too short") from None
        except XcpError as exc:
            self.errors += 1
            name = x.ERROR_NAMES.get(exc.code, hex(exc.code))
            self.refusals[name] = self.refusals.get(name, 0) + 1
            if exc.code == x.ERR_ACCESS_LOCKED and cmd == x.UNLOCK:
                self.connected = False      # a wrong key ends the session
            if cmd == x.DOWNLOAD and len(cto) > 1 and MAX_CTO - 2 < cto[1] <= MAX_BS * (
                    MAX_CTO - 2):
                self.refused_left = cto[1] - (MAX_CTO - 2)
            return [bytes([x.ERR, exc.code])]

    def take_changes(self) -> list[Change]:
        out, self.changes = self.changes, []
        return out

    # ---------------------------------------------------------------- session
    def _connect(self, c: bytes) -> list[bytes]:
        if c[1] != 0:
            raise XcpError(x.ERR_OUT_OF_RANGE, f"CONNECT mode {c[1]} (only normal)")
        self.connected, self.protection, self.seed = True, LOCKABLE, None
        comm = 0x40 | 0x80          # slave block mode, GET_COMM_MODE_INFO; Intel, bytes
        return [struct.pack("<BBBBHBB", x.RES, x.RES_CAL_PAG | x.RES_DAQ, comm, MAX_CTO,
                            MAX_DTO, XCP_VERSION >> 8, XCP_CAN_VERSION >> 8)]

    def _disconnect(self, c: bytes) -> list[bytes]:
        self.connected, self.protection = False, LOCKABLE
        return [bytes([x.RES])]

    def _status(self, c: bytes) -> list[bytes]:
        session = x.SS_DAQ_RUNNING if self.daq.running else 0
        return [struct.pack("<BBBBH", x.RES, session, self.protection, 0, 0)]

    def _synch(self, c: bytes) -> list[bytes]:
        raise XcpError(x.ERR_CMD_SYNCH, "synch")

    def _comm_mode_info(self, c: bytes) -> list[bytes]:
        # master block mode (DOWNLOAD_NEXT), MAX_BS, MIN_ST 0, no queue; driver version 1.0
        return [struct.pack("<BBBBBBBB", x.RES, 0, 0x01, 0, MAX_BS, 0, 0, 0x10)]

    def _get_id(self, c: bytes) -> list[bytes]:
        kind = c[1]
        texts = {0: "SUSPENSION_ECU " + self.memory.image.epk, 1: x.A2L_NAME,
                 4: self.memory.image.epk}
        text = texts.get(kind)
        if text is None:
            return [struct.pack("<BBHI", x.RES, 0, 0, 0)]       # (not available: length 0)
        self.mta = self.memory.text_address(text)
        return [struct.pack("<BBHI", x.RES, 0, 0, len(text))]

    def _get_seed(self, c: bytes) -> list[bytes]:
        mode, resource = c[1], c[2]
        if mode != 0 or resource not in (x.RES_CAL_PAG, x.RES_DAQ, x.RES_STIM, x.RES_PGM):
            raise XcpError(x.ERR_OUT_OF_RANGE, f"GET_SEED mode {mode} resource {resource}")
        if not self.protection & resource:
            return [bytes([x.RES, 0])]          # (not protected: no seed)
        self.seeds += 1
        self.seed = hmac.new(self.secret, b"hil.xcp seed" + self.seeds.to_bytes(8, "little"),
                             hashlib.sha256).digest()[:SEED_LEN]
        self._seed_for = resource
        return [bytes([x.RES, SEED_LEN]) + self.seed]

    def _unlock(self, c: bytes) -> list[bytes]:
        n = c[1]
        if self.seed is None:
            raise XcpError(x.ERR_SEQUENCE, "UNLOCK without GET_SEED")
        seed, self.seed = self.seed, None
        if n != KEY_LEN or len(c) < 2 + n or not hmac.compare_digest(
                bytes(c[2:2 + n]), key_of(self.secret, seed)):
            raise XcpError(x.ERR_ACCESS_LOCKED, "wrong key")
        self.protection &= ~self._seed_for
        return [bytes([x.RES, self.protection])]

    # ---------------------------------------------------------------- memory
    def _set_mta(self, c: bytes) -> list[bytes]:
        ext, self.mta = struct.unpack_from("<BI", c, 3)
        if ext != 0:
            raise XcpError(x.ERR_OUT_OF_RANGE, f"address extension {ext}")
        return [bytes([x.RES])]

    def _upload(self, c: bytes) -> list[bytes]:
        n = c[1]
        if n == 0 or n > 255:
            raise XcpError(x.ERR_OUT_OF_RANGE, f"UPLOAD of {n} bytes")
        data = self.memory.read(self.mta, n, self.xcp_page)
        self.mta += n
        step = MAX_CTO - 1              # slave block mode: as many RES as it takes
        return [bytes([x.RES]) + data[i:i + step] for i in range(0, n, step)]

    def _short_upload(self, c: bytes) -> list[bytes]:
        n = c[1]
        ext, address = struct.unpack_from("<BI", c, 3)
        if n == 0 or n > MAX_CTO - 1 or ext != 0:
            raise XcpError(x.ERR_OUT_OF_RANGE, f"SHORT_UPLOAD of {n} bytes, extension {ext}")
        data = self.memory.read(address, n, self.xcp_page)
        self.mta = address + n
        return [bytes([x.RES]) + data]

    def _write(self, address: int, data: bytes) -> None:
        change = self.memory.write(address, data, self.xcp_page)
        if change is not None:
            self.changes.append(change)

    def _download(self, c: bytes) -> list[bytes]:
        n = c[1]
        first = MAX_CTO - 2
        if n == 0 or n > MAX_BS * first:
            raise XcpError(x.ERR_OUT_OF_RANGE, f"DOWNLOAD of {n} bytes")
        data = bytes(c[2:2 + min(n, first)])
        if len(data) < min(n, first):
            raise XcpError(x.ERR_CMD_SYNTAX, "DOWNLOAD shorter than its length")
        if n > first:                   # master block mode: DOWNLOAD_NEXT brings the rest
            self.block = (n - len(data), bytearray(data))
            return []
        address, self.mta = self.mta, self.mta + n
        self._write(address, data)
        return [bytes([x.RES])]

    def _download_next(self, c: bytes) -> list[bytes]:
        if self.block is None:
            raise XcpError(x.ERR_SEQUENCE, "DOWNLOAD_NEXT without DOWNLOAD")
        left, buf = self.block
        n = c[1]
        if n != left:
            self.block = None
            raise XcpError(x.ERR_SEQUENCE, f"DOWNLOAD_NEXT says {n} bytes left, not {left}")
        part = bytes(c[2:2 + min(n, MAX_CTO - 2)])
        buf += part
        left -= len(part)
        if left > 0:
            self.block = (left, buf)
            return []
        self.block = None
        address, self.mta = self.mta, self.mta + len(buf)
        self._write(address, bytes(buf))
        return [bytes([x.RES])]

    def _short_download(self, c: bytes) -> list[bytes]:
        n = c[1]
        ext, address = struct.unpack_from("<BI", c, 3)
        data = bytes(c[8:8 + n])
        if n == 0 or len(data) != n or ext != 0:
            raise XcpError(x.ERR_OUT_OF_RANGE, f"SHORT_DOWNLOAD of {n} bytes: "
                                               f"{len(data)} fit in a {MAX_CTO}-byte CTO")
        self._write(address, data)
        self.mta = address + n
        return [bytes([x.RES])]

    # ---------------------------------------------------------------- pages
    def _set_cal_page(self, c: bytes) -> list[bytes]:
        mode, segment, page = c[1], c[2], c[3]
        if not mode & (x.PAGE_ECU | x.PAGE_XCP):
            raise XcpError(x.ERR_MODE_NOT_VALID, f"SET_CAL_PAGE mode {mode}")
        if segment != 0 and not mode & x.PAGE_ALL:
            raise XcpError(x.ERR_SEGMENT_NOT_VALID, f"segment {segment}")
        self.memory.page_valid(page)
        if mode & x.PAGE_XCP:
            self.xcp_page = page
        if mode & x.PAGE_ECU and page != self.ecu_page:
            self.ecu_page, self.page_change = page, True
        return [bytes([x.RES])]

    def _get_cal_page(self, c: bytes) -> list[bytes]:
        mode, segment = c[1], c[2]
        if segment != 0:
            raise XcpError(x.ERR_SEGMENT_NOT_VALID, f"segment {segment}")
        if mode not in (x.PAGE_ECU, x.PAGE_XCP):
            raise XcpError(x.ERR_MODE_NOT_VALID, f"GET_CAL_PAGE mode {mode}")
        page = self.ecu_page if mode == x.PAGE_ECU else self.xcp_page
        return [bytes([x.RES, 0, 0, page])]

    def _pag_info(self, c: bytes) -> list[bytes]:
        return [bytes([x.RES, 1, 0])]            # one segment, no FREEZE

    # ---------------------------------------------------------------- DAQ
    def _daq_processor_info(self, c: bytes) -> list[bytes]:
        props = 0x01 | 0x02 | 0x10 | 0x40        # dynamic, prescaler, timestamps, overload PID
        return [struct.pack("<BBHHBB", x.RES, props, MAX_DAQ, len(EVENTS), 0, 0x00)]

    def _daq_resolution_info(self, c: bytes) -> list[bytes]:
        ts_mode = 0x04 | 0x08 | (0x3 << 4)       # 4 bytes, fixed, 1 us
        return [struct.pack("<BBBBBBH", x.RES, 1, MAX_ODT_ENTRY_SIZE, 1, 0, ts_mode,
                            TIMESTAMP_TICKS)]

    def _daq_event_info(self, c: bytes) -> list[bytes]:
        (event,) = struct.unpack_from("<H", c, 2)
        if not 0 <= event < len(EVENTS):
            raise XcpError(x.ERR_OUT_OF_RANGE, f"no event channel {event}")
        name, short, _, ms = EVENTS[event]
        self.mta = self.memory.text_address(short)
        return [struct.pack("<BBBBBBB", x.RES, 0x04, 0xFF, len(short), ms, 6, 0)]

    def _free_daq(self, c: bytes) -> list[bytes]:
        self.daq.free()
        return [bytes([x.RES])]

    def _alloc_daq(self, c: bytes) -> list[bytes]:
        self.daq.alloc_daq(struct.unpack_from("<H", c, 2)[0])
        return [bytes([x.RES])]

    def _alloc_odt(self, c: bytes) -> list[bytes]:
        daq, n = struct.unpack_from("<HB", c, 2)
        self.daq.alloc_odt(daq, n)
        return [bytes([x.RES])]

    def _alloc_odt_entry(self, c: bytes) -> list[bytes]:
        daq, odt, n = struct.unpack_from("<HBB", c, 2)
        self.daq.alloc_entry(daq, odt, n)
        return [bytes([x.RES])]

    def _set_daq_ptr(self, c: bytes) -> list[bytes]:
        daq, odt, entry = struct.unpack_from("<HBB", c, 2)
        self.daq.set_ptr(daq, odt, entry)
        return [bytes([x.RES])]

    def _write_daq(self, c: bytes) -> list[bytes]:
        bit, size, ext, address = struct.unpack_from("<BBBI", c, 1)
        if ext != 0:
            raise XcpError(x.ERR_OUT_OF_RANGE, f"address extension {ext}")
        self.daq.write(bit, size, address)
        return [bytes([x.RES])]

    def _set_daq_list_mode(self, c: bytes) -> list[bytes]:
        mode, daq, event, prescaler, priority = struct.unpack_from("<BHHBB", c, 1)
        self.daq.set_mode(mode, daq, event, prescaler, priority)
        return [bytes([x.RES])]

    def _start_stop_daq_list(self, c: bytes) -> list[bytes]:
        mode, daq = struct.unpack_from("<BH", c, 1)
        return [bytes([x.RES, self.daq.start_stop(mode, daq)])]

    def _start_stop_synch(self, c: bytes) -> list[bytes]:
        self.daq.synch(c[1])
        return [bytes([x.RES])]

    def _daq_clock(self, c: bytes) -> list[bytes]:
        return [struct.pack("<BBBBI", x.RES, 0, 0, 0, (self.tick() * 1000) & 0xFFFFFFFF)]


_HANDLERS = {
    x.CONNECT: Slave._connect, x.DISCONNECT: Slave._disconnect, x.GET_STATUS: Slave._status,
    x.SYNCH: Slave._synch, x.GET_COMM_MODE_INFO: Slave._comm_mode_info,
    x.GET_ID: Slave._get_id, x.GET_SEED: Slave._get_seed, x.UNLOCK: Slave._unlock,
    x.SET_MTA: Slave._set_mta, x.UPLOAD: Slave._upload, x.SHORT_UPLOAD: Slave._short_upload,
    x.DOWNLOAD: Slave._download, x.DOWNLOAD_NEXT: Slave._download_next,
    x.SHORT_DOWNLOAD: Slave._short_download, x.SET_CAL_PAGE: Slave._set_cal_page,
    x.GET_CAL_PAGE: Slave._get_cal_page, x.GET_PAG_PROCESSOR_INFO: Slave._pag_info,
    x.GET_DAQ_PROCESSOR_INFO: Slave._daq_processor_info,
    x.GET_DAQ_RESOLUTION_INFO: Slave._daq_resolution_info,
    x.GET_DAQ_EVENT_INFO: Slave._daq_event_info, x.FREE_DAQ: Slave._free_daq,
    x.ALLOC_DAQ: Slave._alloc_daq, x.ALLOC_ODT: Slave._alloc_odt,
    x.ALLOC_ODT_ENTRY: Slave._alloc_odt_entry, x.SET_DAQ_PTR: Slave._set_daq_ptr,
    x.WRITE_DAQ: Slave._write_daq, x.SET_DAQ_LIST_MODE: Slave._set_daq_list_mode,
    x.START_STOP_DAQ_LIST: Slave._start_stop_daq_list,
    x.START_STOP_SYNCH: Slave._start_stop_synch, x.GET_DAQ_CLOCK: Slave._daq_clock,
}
