"""The ECU node's XCP port: the slave over the node's live records, its frames on the DBC's
``XCP_CMD``/``XCP_RES``, its calibration applied between ticks and its DAQ sampled at the
tick's end (``hil.nodes.ecu.EcuNode`` calls ``on_frame``, ``before_tick``, ``after_tick``)."""

from __future__ import annotations

import hashlib
import hmac

from calib.image import Image
from firmware.layout import params_record
from hil.transport.busload import dbc_bits_per_s
from hil.xcp.daq import Daq
from hil.xcp.memory import REFERENCE, Memory
from hil.xcp.slave import Slave

PAD = 0x00


def xcp_secret(key: bytes) -> bytes:
    """The XCP seed-and-key secret of a run: derived from its key (the run's key file)."""
    return hmac.new(key, b"hil.xcp secret", hashlib.sha256).digest()


class XcpPort:
    def __init__(self, ecu, codec, key: bytes, bitrate: float = 500_000.0):
        self.ecu = ecu                              # firmware.ecu.Ecu
        self.image = Image(ecu.params)
        self.res_id = codec.message("XCP_RES").frame_id
        self.T = self.image.T                       # the FX segment (made in both paths)
        self.memory = Memory(self.image, self._records)
        self.daq = Daq(self.memory, dbc_bits_per_s(codec), bitrate)
        self.slave = Slave(self.memory, self.daq, xcp_secret(key), tick=lambda: ecu.tick)
        self.log: list[dict] = []                  # every calibration applied, with its tick
        self.sent = 0                               # XCP_RES frames

    def _records(self) -> dict:
        e = self.ecu
        return {"T": self.T, "S": e.S, "I": e.I, "O": e.O}

    def _frames(self, payloads) -> list:
        self.sent += len(payloads)
        return [(self.res_id, p.ljust(8, bytes([PAD]))) for p in payloads]

    def on_frame(self, data: bytes) -> list:
        return self._frames(self.slave.handle(bytes(data)))

    def before_tick(self) -> None:
        """Between two ticks: the accepted writes (each whole, in order), a page switch."""
        changes = self.slave.take_changes()
        for ch in changes:
            self.log.append({"tick": self.ecu.tick + 1, "objects": ch.objects})
        if changes or self.slave.page_change:
            self.slave.page_change = False
            m = self.memory
            ref = self.slave.ecu_page == REFERENCE
            self._use(*((self.image.params, self.image.P, self.image.tables) if ref
                        else (m.params, m.working, m.tables)))

    def _use(self, p, P, tables) -> None:
        e = self.ecu
        e.params, e.P = p, P
        self.T = params_record(tables)
        if e.T is not None:
            e.T = self.T

    def after_tick(self) -> list:
        return self._frames(self.daq.sample(self.ecu.tick)) if self.daq.running else []

    def summary(self) -> dict:
        s = self.slave
        return {"requests": s.requests, "errors": s.errors, "refusals": dict(s.refusals),
                "dtos": self.daq.dtos, "calibrations": self.log,
                "ecu_page": s.ecu_page}
