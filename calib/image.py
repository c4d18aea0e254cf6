"""The ECU's memory image, as a calibration tool addresses it (XCP, the A2L of ``calib.a2l``).

The image is the compiled tick's own records (``firmware.layout``), byte for byte, each at a
base address:

    IDENT 0x00000100  the image's identifier (ASCII), read by the master after CONNECT
    CAL   0x00010000  the calibration (``EcuParams`` record P: what the float path and the
                      fixed path's estimator read; two pages, reference and working)
    FX    0x00020000  the fixed-point path's tables (``FxTables`` record T: the calibration
                      compiled to the Q-formats that path reads; derived, read-only)
    RAM   0x20000000  the state S, then the tick's inputs I and outputs O (measurement)

A record is packed (numpy's default: no padding, little-endian), as the packed C structs of
``calib.image_c`` are. An object is a field (or, where a fixed-point array's elements have
different formats, one element) with its address, type, conversion, unit and limits.

What may be written: only the fields of ``calib.calpage.WRITABLE``, within their limits
(which follow from the design's own value: a gain to 4x its magnitude, a rate within [0, 1],
a safety threshold only towards earlier entry, a limit only down). Every other calibration
field is read-only: the discretised model and what is derived from it (Phi, Gamma, H, ...,
the FDI bank), the ADC and plant constants, the fault detection and the safety relevance of
each fault. The FX tables are re-derived from CAL whenever CAL changes, in the formats the
ECU was built with (``calib.fx_tables.pinned``), so a write counts in both paths.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Optional

import numpy as np

from calib.calpage import WRITABLE, limits
from calib.fx_tables import build_tables
from firmware.ecu import inputs, outputs, state_dtype
from firmware.fx import tables as fxt
from firmware.layout import params_record
from firmware.params import MODE_NAMES, EcuParams

EPK_BASE, CAL_BASE, FX_BASE, RAM_BASE = 0x100, 0x10000, 0x20000, 0x20000000
ALIGN_RAM = 0x100           # the inputs and outputs start on a 256-byte boundary
EPK_LEN = 32

# A2L datatypes of the records' numpy kinds
DATATYPE = {"f8": "FLOAT64_IEEE", "i8": "A_INT64", "i4": "SLONG", "u1": "UBYTE"}
_LIMIT = {"f8": 1e300, "i8": 2.0 ** 63, "i4": 2.0 ** 31, "u1": 255.0}


@dataclasses.dataclass(frozen=True)
class Segment:
    name: str
    base: int
    size: int
    record: str                 # "EPK", "P", "T", "S", "I", "O"
    writable: bool


@dataclasses.dataclass(frozen=True)
class Obj:
    """One A2L object: ``path`` is the field's path in its record, ``index`` the element
    (flat, or None: the whole field)."""

    name: str
    segment: str
    address: int
    dtype: str                  # "f8", "i8", "i4", "u1"
    shape: tuple                # () for a scalar
    path: tuple
    index: Optional[int] = None
    frac: Optional[int] = None  # fixed point: physical = raw * 2^-frac
    factor: Optional[float] = None   # a decimal scaling (physical = raw * factor)
    unit: str = ""
    lower: float = 0.0
    upper: float = 0.0
    writable: bool = False
    enum: Optional[tuple] = None     # names of the raw values 0, 1, ...
    axis: Optional[str] = None       # the object whose values are this curve's axis
    text: str = ""

    @property
    def size(self) -> int:
        return int(np.dtype(self.dtype).itemsize * int(np.prod(self.shape, dtype=np.int64)))

    @property
    def characteristic(self) -> bool:
        return self.segment in ("CAL", "FX")


# measurement: path -> (unit, scaling, text); the outputs' integer scalings: an int is a
# fixed-point format (its fractional bits), a float a decimal factor
_MEAS = {
    "out.duty_q15": ("", 15, "PWM duty, Q15 (signed: direction)"),
    "out.force_cmd_n": ("N", None, "force command"),
    "out.road_est_um": ("m", 1e-6, "road height estimate"),
    "out.dtd_est_um": ("m", 1e-6, "tyre deflection estimate"),
    "out.gq_est_log_c": ("grade/100", None, "log4(Gq/Gq,A) x 100; -32768 unknown"),
    "out.ba_rms_mmps2": ("m/s^2", 1e-3, "body acceleration RMS"),
    "out.dtd_rms_um": ("m", 1e-6, "tyre deflection RMS"),
    "ecu.akf.x": ("SI", None, "AKF estimate [zs' m/s, zt' m/s, zs m, zt m, zf m]"),
    "ecu.fdi.supply_v": ("V", None, "storage supply voltage"),
    "ecu.fdi.nis": ("", None, "FDI: normalised innovation squared per channel"),
    "ecu.bank.stat": ("", None, "FDI bank: statistic per hypothesis"),
    "ecu.grade.gq": ("m^3", None, "road intensity estimate Gq"),
}
_ENUMS = {"out.active_mode": MODE_NAMES, "out.recommended_mode": MODE_NAMES,
          "ecu.modes.active_mode": MODE_NAMES, "ecu.modes.recommended": MODE_NAMES}
# the fixed-point state's formats (firmware.fx.path): field -> fractional bits (per element)
_FX_STATE = {
    "x": fxt.STATE_FRAC, "xp": fxt.STATE_FRAC, "resid": fxt.MEAS_FRAC, "eps": fxt.MEAS_FRAC,
    "ba": fxt.F_ACC, "wa": fxt.F_ACC, "defl": fxt.F_POS, "cur": fxt.F_CUR,
    "i_prev": fxt.F_CUR, "i_ref_prev": fxt.F_CUR, "integ": fxt.F_VOLT, "voltage": fxt.F_VOLT,
    "force": fxt.F_FORCE, "force_meas": fxt.F_FORCE, "force_known_prev": fxt.F_FORCE,
    "duty": 15, "w_h": fxt.F_W, "b_h": fxt.F_W, "w_o": fxt.F_W, "b_o": fxt.F_W,
    "dw_h": fxt.F_W, "db_h": fxt.F_W, "dw_o": fxt.F_W, "db_o": fxt.F_W,
    "xin": fxt.F_NN, "h": fxt.F_NN, "g": fxt.F_NN,
}
# a curve over an axis (CAL): values -> axis points
CURVES = {"grade.var_per_gq": "grade.speed_grid"}


def _leaves(dt: np.dtype, path=(), off=0):
    """(path, offset, base kind, shape) of every leaf field, in layout order."""
    for n in dt.names:
        f, o = dt.fields[n][:2]
        if f.names:
            yield from _leaves(f, path + (n,), off + o)
        elif f.subdtype is not None and f.subdtype[0].names:
            # (not in these records: their tables are structs of arrays)
            raise TypeError(f"{'.'.join(path + (n,))}: an array of records")
        else:
            base, shape = (f.subdtype if f.subdtype is not None else (f, ()))
            yield path + (n,), off + o, base.str.lstrip("<|"), tuple(shape)


def field(rec: np.ndarray, path: tuple):
    v = rec[0]
    for p in path:
        v = v[p]
    return v


class Image:
    """The segments and objects of calibration ``p`` (its records, made here)."""

    def __init__(self, p: EcuParams):
        self.params = p
        self.P = params_record(p)
        self.tables = build_tables(p)          # (their formats are the A2L's)
        self.T = params_record(self.tables)
        self.S_dtype = state_dtype(p)
        self.I_dtype, self.O_dtype = inputs().dtype, outputs().dtype
        i_base = _align(RAM_BASE + self.S_dtype.itemsize)
        o_base = _align(i_base + self.I_dtype.itemsize)
        self.segments = (
            Segment("IDENT", EPK_BASE, EPK_LEN, "EPK", False),
            Segment("CAL", CAL_BASE, self.P.dtype.itemsize, "P", True),
            Segment("FX", FX_BASE, self.T.dtype.itemsize, "T", False),
            Segment("STATE", RAM_BASE, self.S_dtype.itemsize, "S", False),
            Segment("INPUTS", i_base, self.I_dtype.itemsize, "I", False),
            Segment("OUTPUTS", o_base, self.O_dtype.itemsize, "O", False))
        objs = self._cal() + self._fx() + self._meas()
        self.objects = {o.name: o for o in objs}
        if len(self.objects) != len(objs):
            raise ValueError("duplicate object names in the image")
        self.epk = self._epk()
        missing = sorted(n for n in WRITABLE if "cal." + n not in self.objects)
        if missing:
            raise ValueError(f"WRITABLE names fields the calibration does not have: {missing}")

    def segment(self, name: str) -> Segment:
        return next(s for s in self.segments if s.name == name)

    def _epk(self) -> str:
        """What the A2L says of this memory: changes with the software version, the layout
        of any record (the vehicle's array sizes among them) and how each object is
        described (its conversion, as the fixed-point format of an ``fx.`` object, and its
        limits: another car's or gains file's), not with the values alone (a run's mode:
        the same A2L describes it). A master with another A2L can tell."""
        h = hashlib.sha256(self.params.software_version.encode())
        for dt in (self.P.dtype, self.T.dtype, self.S_dtype, self.I_dtype, self.O_dtype):
            h.update(repr(dt.descr).encode())
        for name, o in sorted(self.objects.items()):
            h.update(repr((name, o.frac, o.factor, o.lower, o.upper)).encode())
        return ("SUSP_ECU_" + h.hexdigest())[:EPK_LEN]

    def _cal(self) -> list[Obj]:
        out = []
        for path, off, kind, shape in _leaves(self.P.dtype):
            name = ".".join(path)
            v = np.asarray(field(self.P, path), dtype=float)
            rule = WRITABLE.get(name)
            if rule is not None:
                _, unit, text = rule
                lo, hi = limits(name, v)
            else:
                unit, text = "", "read-only"
                lo, hi = float(np.min(v)), float(np.max(v))
            out.append(Obj("cal." + name, "CAL", CAL_BASE + off, kind, shape, path,
                           unit=unit, lower=lo, upper=hi, writable=rule is not None,
                           axis=("cal." + CURVES[name]) if name in CURVES else None,
                           text=text))
        return out

    def _fx(self) -> list[Obj]:
        """The fixed-point tables: a constant's mantissa ``m`` with its format (one object
        per element where the elements' formats differ), its ``frac`` as an integer."""
        out = []
        T = self.T
        leaves = {path: (off, kind, shape) for path, off, kind, shape in _leaves(T.dtype)}
        for path, (off, kind, shape) in leaves.items():
            if path[-1] == "value":         # (the float each constant stands for: docs only)
                continue
            name = "fx." + ".".join(path)
            if path[-1] == "m":
                fracs = np.asarray(field(T, path[:-1] + ("frac",))).ravel()
                m = np.asarray(field(T, path)).ravel()
                base = "fx." + ".".join(path[:-1])
                if len(set(fracs.tolist())) == 1:
                    f = int(fracs[0])
                    out.append(Obj(base, "FX", FX_BASE + off, kind, shape, path, frac=f,
                                   lower=float(m.min()) * 2.0 ** -f,
                                   upper=float(m.max()) * 2.0 ** -f, text="read-only"))
                    continue
                for i, (mi, f) in enumerate(zip(m.tolist(), fracs.tolist())):
                    out.append(Obj(f"{base}[{i}]", "FX", FX_BASE + off + 8 * i, kind, (),
                                   path, index=i, frac=int(f), lower=mi * 2.0 ** -f,
                                   upper=mi * 2.0 ** -f, text="read-only"))
                continue
            v = np.asarray(field(T, path), dtype=float)
            out.append(Obj(name, "FX", FX_BASE + off, kind, shape, path,
                           lower=float(v.min()), upper=float(v.max()), text="read-only"))
        return out

    def _meas(self) -> list[Obj]:
        out = []
        for prefix, seg, dt in (("ecu", "STATE", self.S_dtype), ("in", "INPUTS", self.I_dtype),
                                ("out", "OUTPUTS", self.O_dtype)):
            base = self.segment(seg).base
            for path, off, kind, shape in _leaves(dt):
                name = prefix + "." + ".".join(path)
                fracs = _FX_STATE.get(path[-1]) if path[0] == "fx" else None
                if isinstance(fracs, tuple):
                    for i in range(int(np.prod(shape))):
                        out.append(_meas_obj(f"{name}[{i}]", seg, base + off + 8 * i, kind,
                                             (), path, index=i, frac=fracs[i]))
                    continue
                unit, scale, text = _MEAS.get(name, ("", None, ""))
                if isinstance(scale, int):
                    fracs, scale = scale, None
                out.append(_meas_obj(name, seg, base + off, kind, shape, path, frac=fracs,
                                     factor=scale, unit=unit, text=text,
                                     enum=_ENUMS.get(name)))
        return out

    # reading and writing by address (the slave's UPLOAD/DOWNLOAD go through these)
    def find(self, address: int, size: int) -> Optional[Segment]:
        """The segment holding [address, address + size), or None."""
        for s in self.segments:
            if s.base <= address and address + size <= s.base + s.size:
                return s
        return None

    def objects_in(self, address: int, size: int) -> list[Obj]:
        """The objects that [address, address + size) touches."""
        end = address + size
        return [o for o in self.objects.values()
                if o.address < end and address < o.address + o.size]


def _meas_obj(name, seg, address, kind, shape, path, index=None, frac=None, factor=None,
              unit="", text="", enum=None) -> Obj:
    lim = _LIMIT[kind]
    lo, hi = (0.0, lim) if kind == "u1" else (-lim, lim if kind == "f8" else lim - 1)
    scale = 2.0 ** -frac if frac is not None else (factor or 1.0)
    if enum is not None:
        lo, hi = 0.0, float(len(enum) - 1)
    return Obj(name, seg, address, kind, shape, path, index=index, frac=frac, factor=factor,
               unit=unit, lower=lo * scale, upper=hi * scale, enum=enum, text=text)


def _align(a: int) -> int:
    return (a + ALIGN_RAM - 1) // ALIGN_RAM * ALIGN_RAM
