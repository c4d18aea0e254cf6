"""XCP 1.4 codes (ASAM MCD-1 XCP, part 2): commands, packet identifiers, errors, resources."""

from __future__ import annotations

# packet identifiers, slave to master
RES, ERR, EV, SERV = 0xFF, 0xFE, 0xFD, 0xFC

# commands
CONNECT, DISCONNECT, GET_STATUS, SYNCH = 0xFF, 0xFE, 0xFD, 0xFC
GET_COMM_MODE_INFO, GET_ID, GET_SEED, UNLOCK = 0xFB, 0xFA, 0xF8, 0xF7
SET_MTA, UPLOAD, SHORT_UPLOAD = 0xF6, 0xF5, 0xF4
DOWNLOAD, DOWNLOAD_NEXT, SHORT_DOWNLOAD = 0xF0, 0xEF, 0xED
SET_CAL_PAGE, GET_CAL_PAGE, GET_PAG_PROCESSOR_INFO = 0xEB, 0xEA, 0xE9
SET_DAQ_PTR, WRITE_DAQ, SET_DAQ_LIST_MODE = 0xE2, 0xE1, 0xE0
START_STOP_DAQ_LIST, START_STOP_SYNCH, GET_DAQ_CLOCK = 0xDE, 0xDD, 0xDC
GET_DAQ_PROCESSOR_INFO, GET_DAQ_RESOLUTION_INFO, GET_DAQ_EVENT_INFO = 0xDA, 0xD9, 0xD7
FREE_DAQ, ALLOC_DAQ, ALLOC_ODT, ALLOC_ODT_ENTRY = 0xD6, 0xD5, 0xD4, 0xD3

# error codes
ERR_CMD_SYNCH = 0x00
ERR_CMD_BUSY = 0x10
ERR_DAQ_ACTIVE = 0x11
ERR_CMD_UNKNOWN = 0x20
ERR_CMD_SYNTAX = 0x21
ERR_OUT_OF_RANGE = 0x22
ERR_WRITE_PROTECTED = 0x23
ERR_ACCESS_DENIED = 0x24
ERR_ACCESS_LOCKED = 0x25
ERR_PAGE_NOT_VALID = 0x26
ERR_MODE_NOT_VALID = 0x27
ERR_SEGMENT_NOT_VALID = 0x28
ERR_SEQUENCE = 0x29
ERR_DAQ_CONFIG = 0x2A
ERR_MEMORY_OVERFLOW = 0x30
ERR_GENERIC = 0x31

ERROR_NAMES = {v: k for k, v in globals().items() if k.startswith("ERR_")}

# resources (CONNECT's RESOURCE, GET_STATUS's protection, GET_SEED's resource)
RES_CAL_PAG, RES_DAQ, RES_STIM, RES_PGM = 0x01, 0x04, 0x08, 0x10

# session status bits
SS_DAQ_RUNNING = 0x40

# SET_CAL_PAGE / GET_CAL_PAGE mode
PAGE_ECU, PAGE_XCP, PAGE_ALL = 0x01, 0x02, 0x80

# the identifier the master's GET_ID type 1 asks for: the A2L's name without extension
A2L_NAME = "ecu"


class XcpError(Exception):
    """A refusal: the ERR packet's code."""

    def __init__(self, code: int, why: str = ""):
        super().__init__(f"{ERROR_NAMES.get(code, hex(code))}: {why}")
        self.code = code
