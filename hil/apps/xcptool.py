"""``python -m hil xcp``: a calibration tool on pyxcp against a running bench.

    python -m hil xcp info                                [bus] --key-file DIR/secoc.key ...
    python -m hil xcp get NAME
    python -m hil xcp set NAME VALUE[,VALUE...]
    python -m hil xcp measure NAME... --event 1ms|10ms [--prescaler N] --seconds S --out F.mf4

The bus is the hub (``-i remote -c ws://127.0.0.1:PORT/ --secret-file DIR/hub.secret``: the
tester authenticates as the DBC's TESTER, the only sender of XCP_CMD) or vcan0 (``-i
socketcan -c vcan0``). ``--key-file`` is the run's key file: the seed-and-key secret is
derived from it. Names and conversions come from the A2L (pya2ldb, ``--a2l``, default
c/generated/ecu.a2l); after CONNECT the ECU's EPK is checked against the A2L's. A NAME may
pick one element: ``cal.control.k_safety[2]``. Exit 0 done, 1 the ECU refused, did not
answer or lost data, 2 bad input.
"""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from calib.a2l import MAX_BS, MAX_CTO

ROOT = Path(__file__).resolve().parents[2]
A2L_PATH = ROOT / "c" / "generated" / "ecu.a2l"
DTYPES = {"FLOAT64_IEEE": "<f8", "A_INT64": "<i8", "SLONG": "<i4", "UBYTE": "u1"}
DAQ_TYPES = {"<i4": "I32", "u1": "U8"}


def push(x, address: int, data: bytes) -> None:
    """Write ``data`` at ``address`` in master block mode: blocks of MAX_BS frames (240 bytes,
    whole doubles), each a DOWNLOAD and its DOWNLOAD_NEXTs, one response per block. (pyxcp
    0.29.20's ``Master.push`` sends the tail of a 7 to 11 byte block as a second DOWNLOAD,
    which the slave refuses as out of sequence: this uses its DOWNLOAD and DOWNLOAD_NEXT.)"""
    step = MAX_CTO - 2
    block = MAX_BS * step
    x.setMta(address)
    for off in range(0, len(data), block):
        chunk = data[off:off + block]
        if len(chunk) <= step:
            x.download(chunk)
            continue
        x.download(chunk[:step], block_mode_length=len(chunk))
        rest = chunk[step:]
        while rest:
            part, rest = rest[:step], rest[step:]
            x.downloadNext(part, len(part) + len(rest), last=not rest)


@contextmanager
def _parser_messages():
    """What pya2ldb's C++ parser writes on stdout and stderr (file descriptors 1 and 2), as
    lines: its errors are how a bad A2L shows; its note that the file has no A2ML block is
    dropped, anything else is passed on to stderr."""
    import os
    import tempfile

    said: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        try:
            yield said
        finally:
            for fd, old in zip((1, 2), saved):
                os.dup2(old, fd)
                os.close(old)
            tmp.seek(0)
            said += tmp.read().decode(errors="replace").splitlines()
    for line in said:
        if "Empty AML section" not in line and "[error]" not in line.lower():
            print(line, file=sys.stderr)


@dataclass(frozen=True)
class Item:
    """An A2L object as the tool uses it."""

    name: str
    address: int
    dtype: str
    count: int
    factor: float
    unit: str
    lower: float
    upper: float
    writable: bool
    enum: Optional[tuple] = None

    @property
    def size(self) -> int:
        return np.dtype(self.dtype).itemsize * self.count

    def element(self, i: int) -> "Item":
        if not 0 <= i < self.count:
            raise KeyError(f"{self.name} has {self.count} elements, not [{i}]")
        from dataclasses import replace

        return replace(self, name=f"{self.name}[{i}]", count=1,
                       address=self.address + i * np.dtype(self.dtype).itemsize)

    def physical(self, raw: bytes) -> list:
        v = np.frombuffer(raw[:self.size], self.dtype).astype(float) * self.factor
        return v.tolist()


class A2l:
    """What the tool needs of the A2L: every object by name, the EPK and its address."""

    def __init__(self, path: Path = A2L_PATH):
        import pya2l
        import pya2l.model as model

        if not path.is_file():
            raise FileNotFoundError(f"no A2L at {path} (make tables writes it)")
        logging.disable(logging.WARNING)        # (pya2ldb logs its progress at INFO)
        try:
            with _parser_messages() as said:
                s = pya2l.import_a2l(str(path), in_memory=True, loglevel="ERROR",
                                     progress_bar=False)
        finally:
            logging.disable(logging.NOTSET)
        errors = [line for line in said if "[error]" in line.lower()]
        if errors:
            raise ValueError(f"{path}: the A2L does not parse: {errors[0].strip()}")
        cms = {c.name: c for c in s.query(model.CompuMethod).all()}
        layouts = {r.name: r for r in s.query(model.RecordLayout).all()}
        self.items: dict[str, Item] = {}

        def conv(name):
            c = cms.get(name)
            if c is None:
                return 1.0, None
            if c.conversionType == "TAB_VERB":
                vt = s.query(model.CompuVtab).filter_by(name=c.compu_tab_ref.conversionTable).one()
                return 1.0, tuple(p.outVal for p in sorted(vt.pairs, key=lambda p: p.inVal))
            return float(c.coeffs_linear.a), None

        for m in s.query(model.Measurement).all():
            f, enum = conv(m.conversion)
            n = int(np.prod(m.matrix_dim.numbers)) if m.matrix_dim else 1
            self.items[m.name] = Item(m.name, m.ecu_address.address, DTYPES[m.datatype], n, f,
                                      m.phys_unit.unit if m.phys_unit else "", m.lowerLimit,
                                      m.upperLimit, False, enum)
        for c in s.query(model.Characteristic).all():
            f, enum = conv(c.conversion)
            n = int(np.prod(c.matrix_dim.numbers)) if c.matrix_dim else 1
            if c.type == "CURVE":
                n = c.axis_descr[0].maxAxisPoints
            dt = DTYPES[layouts[c.deposit].fnc_values.datatype]
            self.items[c.name] = Item(c.name, c.address, dt, n, f,
                                      c.phys_unit.unit if c.phys_unit else "", c.lowerLimit,
                                      c.upperLimit, not c.read_only, enum)
        for a in s.query(model.AxisPts).all():
            dt = DTYPES[layouts[a.depositAttr].axis_pts_x.datatype]
            self.items[a.name] = Item(a.name, a.address, dt, a.maxAxisPoints, 1.0, "",
                                      a.lowerLimit, a.upperLimit, not a.read_only)
        mp = s.query(model.ModPar).first()
        if mp is None or mp.epk is None or not mp.addr_epk:
            raise ValueError(f"{path}: no EPK and ADDR_EPK in MOD_PAR")
        self.epk, self.epk_address = mp.epk.identifier, mp.addr_epk[0].address
        s.close()

    def item(self, spec: str) -> Item:
        """``NAME`` or ``NAME[i]``."""
        if spec in self.items:
            return self.items[spec]
        name, _, index = spec.partition("[")
        it = self.items.get(name)
        if it is None:
            near = [n for n in self.items if name.split(".")[-1] in n][:5]
            raise KeyError(f"{name}: not in the A2L" + (f" (did you mean {', '.join(near)}?)"
                                                          if near else ""))
        if index:
            try:
                return it.element(int(index.rstrip("]")))
            except ValueError:
                raise KeyError(f"{spec}: the index must be an integer") from None
        return it


def master(bus, key: bytes, policy=None, timeout: float = 2.0):
    """A pyxcp master on ``bus`` (python-can) for this ECU: the DBC's IDs, the seed-and-key
    function of the run's key, refusals as exceptions (XcpResponseError)."""
    from pyxcp.config import create_application_from_config
    from pyxcp.master import Master

    from hil.transport.codec import Codec
    from hil.xcp.port import xcp_secret
    from hil.xcp.slave import key_of

    codec = Codec()
    secret = xcp_secret(key)
    app = create_application_from_config(
        {"Transport": {"CAN": {"can_id_master": codec.message("XCP_CMD").frame_id,
                               "can_id_slave": codec.message("XCP_RES").frame_id,
                               "max_dlc_required": True}},
         "General": {"disable_error_handling": True,
                     "seed_n_key_function": lambda res, seed: key_of(secret, bytes(seed))}},
        log_level=logging.WARNING)
    app.transport.layer = "CAN"
    app.transport.timeout = timeout
    # (pyxcp logs every exception that leaves a Master's context with its traceback; the
    # tool says each refusal in one line)
    logging.getLogger("pyxcp.master").setLevel(logging.CRITICAL)
    return Master("can", config=app, transport_layer_interface=bus, policy=policy)


@contextmanager
def connected(bus, key: bytes, policy=None, timeout: float = 2.0):
    """``master`` as a context that, on leaving, also waits for pyxcp's listener thread
    (its ``close`` only signals it: a bus closed under it logs an error)."""
    x = master(bus, key, policy, timeout)
    try:
        with x:
            yield x
    finally:
        listener = getattr(x.transport, "listener", None)
        if listener is not None and listener.is_alive():
            listener.join(timeout=1.0)


def session(x, a2l: A2l) -> dict:
    """CONNECT, the EPK against the A2L's, GET_COMM_MODE_INFO, unlock: the slave's facts."""
    r = x.connect()
    x.setMta(a2l.epk_address)
    epk = x.upload(len(a2l.epk))[:len(a2l.epk)].decode(errors="replace")
    if epk != a2l.epk:
        raise RuntimeError(f"the ECU's EPK {epk!r} is not the A2L's {a2l.epk!r}: the A2L "
                           "does not describe this ECU's memory (make the run's own: python "
                           "-m tools.tables --vehicle V [--gains G] [--design D] --out DIR, "
                           "then --a2l DIR/ecu.a2l)")
    x.getCommModeInfo()
    x.cond_unlock()
    return {"epk": epk, "max_cto": r.maxCto, "max_dto": r.maxDto,
            "protocol_layer": r.protocolLayerVersion}


def read(x, it: Item) -> list:
    x.setMta(it.address)
    return it.physical(x.upload(it.size))


def encode(it: Item, text: str) -> bytes:
    """VALUE[,VALUE...] in physical units as the raw bytes of ``it`` (ValueError if not)."""
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise ValueError(f"{text!r}: numbers, comma-separated") from None
    if len(values) != it.count:
        raise ValueError(f"{it.name} has {it.count} element(s), got {len(values)}")
    raw = values / it.factor
    if np.dtype(it.dtype).kind in "iu":
        if np.any(raw != np.round(raw)):
            raise ValueError(f"{it.name} is an integer")
        raw = np.round(raw)
    return raw.astype(it.dtype).tobytes()
