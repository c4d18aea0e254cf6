"""The compiled tick's memory: the calibration, the state and a tick's inputs and outputs as
numpy structured records with named fields, nested by stage (``P.adc.lsb[i]``,
``S.akf.x[0]``, ``S.modes.active_mode``), so that numba compiles the stages over them and the
interpreter runs the same source (``NUMBA_DISABLE_JIT=1``).

The calibration record is laid out from ``firmware.params.EcuParams`` field by field (every
number of the dataclasses, nested as they are: this is the calibration image a calibration
tool addresses): a float is ``f8``, an int ``i8``, a bool ``u1``, an array its shape in
``f8``, a tuple of numbers an array; text and hashes (DIDs) stay in the dataclass. The ADC
channels' constants also appear as arrays over the channels (``P.adc.lsb[i]``).

A record is a one-element array (numba's dispatch reads an array's type in 0.2 us, a record
scalar's in 4 us; a recarray's in 1.6 us, so it is one only where the interpreter runs the
tick, ``NUMBA_DISABLE_JIT=1``); ``view`` gives the element with its fields as attributes in
Python.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from firmware import safety
from firmware.adc import CHANNELS
from firmware.kernels import INTERPRETED

# one tick's inputs: the ADC counts in firmware.adc.CHANNELS order (speed last), -1 where no
# valid sample arrived; the supply voltage's counts (-1: no sample this tick); the driver's
# latest request; the receive path's frame-fault bits
# (32-bit integers, as the outputs: a calibration tool's DAQ reads the tick in 4 bytes)
INPUTS = np.dtype([("tick", "i4"), ("counts", "i4", (len(CHANNELS),)), ("supply", "i4"),
                   ("req_kind", "i4"), ("req_mode", "i4"), ("req_counter", "i4"),
                   ("link_faults", "i4")])
# one tick's outputs (firmware.ecu.Outputs' fields, in its order): 32-bit integers, as the
# trace hash packs them (hil.nodes.ecu.HASHED), so that a calibration tool's DAQ carries
# one in 4 bytes of an ODT's 7 (docs/xcp.md)
OUTPUTS = np.dtype([("duty_q15", "i4"), ("regen", "u1"), ("enable", "u1"),
                    ("recommended_mode", "i4"), ("active_mode", "i4"), ("grade", "i4"),
                    ("faults", "i4"), ("reason", "i4"), ("events", "i4"), ("override", "u1"),
                    ("force_cmd_n", "i4"), ("road_est_um", "i4"), ("dtd_est_um", "i4"),
                    ("gq_est_log_c", "i4"), ("ba_rms_mmps2", "i4"), ("dtd_rms_um", "i4"),
                    ("degraded", "i4")])

# fields a calibration may leave out (None), with the value the tick reads instead
_NONE_AS = {"gamma_wheel": lambda p: np.zeros(5)}
# constants the tick reads, computed here once, in Python (``sigma ** 2`` is libm's pow, not
# sigma * sigma: the bits the tick was pinned with)
DERIVED = {
    "AkfParams": (
        ("lift_force_var", lambda a: a.lift_force_sigma_n ** 2),
        ("current_force_var", lambda a: a.current_force_sigma_n ** 2),
        ("stroke_force_var", lambda a: a.stroke_force_sigma_n ** 2),
        ("r_scale", lambda a: np.outer(np.sqrt(a.r_floor), np.sqrt(a.r_floor)))),
    "FdiParams": (("cur_var", lambda f: f.cur_sigma_a ** 2),),
    # the fault bits that open the bridge (firmware.safety: read where the image is laid out)
    "EcuParams": (("safety_relevant", lambda p: safety.SAFETY_RELEVANT),),
}


def _field_dtype(name: str, value, owner) -> object | None:
    if dataclasses.is_dataclass(value):
        return _dtype_of(value)
    if value is None and name in _NONE_AS:
        value = _NONE_AS[name](owner)
    if isinstance(value, bool):
        return "u1"
    if isinstance(value, int):
        return "i8"
    if isinstance(value, float):
        return "f8"
    if isinstance(value, np.ndarray):
        return ("f8", value.shape)
    if isinstance(value, tuple) and value and all(dataclasses.is_dataclass(v) for v in value):
        # a table of constants (firmware.fx.tables.Fx): their fields as arrays
        first = _dtype_of(value[0])
        return np.dtype([(n, first[n].base, (len(value),)) for n in first.names])
    if isinstance(value, tuple) and value and all(isinstance(v, (bool, int, float))
                                                  for v in value):
        kind = "f8" if any(isinstance(v, float) for v in value) else "i8"
        return (kind, (len(value),))
    return None          # text, hashes: not the tick's


def _dtype_of(obj) -> np.dtype:
    fields = []
    for f in dataclasses.fields(obj):
        dt = _field_dtype(f.name, getattr(obj, f.name), obj)
        if dt is not None:
            fields.append((f.name, dt))
    if type(obj).__name__ == "AdcParams":        # the channels' constants as arrays
        n = len(CHANNELS)
        fields += [("range_min", "f8", (n,)), ("lsb", "f8", (n,)), ("full_scale", "i8", (n,))]
    for name, fn in DERIVED.get(type(obj).__name__, ()):
        fields.append((name, _field_dtype(name, fn(obj), obj)))
    return np.dtype(fields)



def _fill(rec, obj) -> None:
    for f in dataclasses.fields(obj):
        if f.name not in rec.dtype.names:
            continue
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _fill(rec[f.name], value)
        elif isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
            for n in rec[f.name].dtype.names:
                rec[f.name][n] = [getattr(v, n) for v in value]
        else:
            if value is None:
                value = _NONE_AS[f.name](obj)
            rec[f.name] = value
    for name, fn in DERIVED.get(type(obj).__name__, ()):
        rec[name] = fn(obj)
    if type(obj).__name__ == "AdcParams":
        for i, name in enumerate(CHANNELS):
            ch = getattr(obj, name)
            rec["range_min"][i], rec["lsb"][i] = ch.range_min, ch.lsb
            rec["full_scale"][i] = ch.full_scale


_CANONICAL: dict = {}


def canonical(dtype: np.dtype) -> np.dtype:
    """The first dtype object equal to ``dtype`` this process made. numba reads an argument's
    type from its dtype object: for a structured dtype it has seen it costs 0.2 us, for an
    equal new object the slow path (measured: a second ECU in a process, 18 us per tick
    against 3.2); so every record of a layout shares one dtype object."""
    return _CANONICAL.setdefault(dtype, dtype)


def params_record(p) -> np.ndarray:
    """The calibration (``EcuParams``, or the fixed-point path's ``FxTables``) as a
    one-element record array (read-only)."""
    rec = np.zeros(1, dtype=canonical(_dtype_of(p)))
    _fill(rec[0], p)
    rec.setflags(write=False)
    return rec.view(np.recarray) if INTERPRETED else rec


def record(dtype) -> np.ndarray:
    """A zeroed one-element record array of ``dtype`` (a recarray where the interpreter runs
    the tick: its elements' fields are attributes, as numba's are)."""
    rec = np.zeros(1, dtype=canonical(np.dtype(dtype)))
    return rec.view(np.recarray) if INTERPRETED else rec


def view(rec: np.ndarray):
    """The element of a one-element record array, its fields as attributes (and written
    through): ``view(state).akf.x``."""
    return rec.view(np.recarray)[0]
