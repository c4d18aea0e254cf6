"""The shipped calibrations as data: one committed, versioned file per shipped vehicle.

A production ECU ships a calibration data set, not the recipe that made it. Each vehicle file
of ``hil/vehicles/`` has its calibration (every number of ``firmware.params.EcuParams``: the
image the A2L describes) in ``calib/data/<vehicle>.json``, written by ``python -m
tools.calibration`` (``make tables``). ``calib.ecu_params.build`` returns it wherever the
design's inputs are the file's (the vehicle as parsed, the design options, the gains file's
bytes, the generator's version: ``calib.ecu_params.design_key``), on every host, without
designing; any other car or option is designed. ``python -m tools.calibration --check`` (``make
tables-check``) designs each shipped car afresh and reports every value that moved.

The file is JSON: each dataclass as an object with its class name, each array as its shape,
dtype and values, floats written as Python's repr (the shortest text that reads back to the
same bits), bytes as hex. ``SUSPENSION_NO_DATA=1`` designs even the shipped cars (the check,
the kernel-variation test).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from firmware import params as fp

DIR = Path(__file__).resolve().parent / "data"
FORMAT = 1
ENV_OFF = "SUSPENSION_NO_DATA"
_CLASSES = {c.__name__: c for c in vars(fp).values()
            if isinstance(c, type) and dataclasses.is_dataclass(c)}


def enabled() -> bool:
    return os.environ.get(ENV_OFF, "") in ("", "0")


def encode(obj):
    """A calibration tree as JSON-able values (``decode`` reads it back to the same bits)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__class__": type(obj).__name__,
                **{f.name: encode(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, np.ndarray):
        return {"__array__": obj.dtype.str, "shape": list(obj.shape),
                "data": [v.item() for v in obj.ravel()]}
    if isinstance(obj, bytes):
        return {"__bytes__": obj.hex()}
    if isinstance(obj, tuple):
        return {"__tuple__": [encode(v) for v in obj]}
    if isinstance(obj, (bool, int, float, str)) or obj is None:
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode a {type(obj).__name__} in a calibration")


def decode(value):
    if isinstance(value, dict):
        if "__class__" in value:
            cls = _CLASSES[value["__class__"]]
            return cls(**{k: decode(v) for k, v in value.items() if k != "__class__"})
        if "__array__" in value:
            return np.ascontiguousarray(np.array(value["data"], dtype=np.dtype(value["__array__"]))
                                        .reshape(value["shape"]))
        if "__bytes__" in value:
            return bytes.fromhex(value["__bytes__"])
        if "__tuple__" in value:
            return tuple(decode(v) for v in value["__tuple__"])
        raise ValueError(f"unknown calibration object {sorted(value)}")
    return value


def image_sha256(p: fp.EcuParams) -> str:
    """SHA-256 of the calibration image (the record the A2L describes, ``firmware.layout``)."""
    from firmware.layout import params_record

    return hashlib.sha256(params_record(p).tobytes()).hexdigest()


def text(p: fp.EcuParams, vehicle: str, design_key: str) -> str:
    """The data file of calibration ``p`` for ``vehicle`` (its file name in hil/vehicles)."""
    doc = {"format": FORMAT, "vehicle": vehicle, "design_key": design_key,
           "calibration_sha256": bytes(p.calibration_sha256).hex(),
           "image_sha256": image_sha256(p), "params": encode(p)}
    return json.dumps(doc, indent=1) + "\n"


def path_for(vehicle: str) -> Path:
    return DIR / f"{Path(vehicle).stem}.json"


@functools.lru_cache(maxsize=1)
def _index() -> dict[str, Path]:
    """{design_key: file} of the committed data sets."""
    out = {}
    for path in sorted(DIR.glob("*.json")):
        try:
            with open(path, encoding="utf-8") as f:
                head = json.load(f)
            out[head["design_key"]] = path
        except (OSError, ValueError, KeyError):
            continue                    # (a broken file is reported by the check, not here)
    return out


@functools.lru_cache(maxsize=8)
def _read(path: Path) -> fp.EcuParams:
    doc = read(path)
    if doc.get("format") != FORMAT:
        raise ValueError(f"{path}: calibration data format {doc.get('format')}, "
                         f"this software reads {FORMAT}")
    p = doc["params"]
    if image_sha256(p) != doc["image_sha256"]:
        raise ValueError(f"{path}: the calibration image's SHA-256 is not the one recorded "
                         f"(a damaged or hand-edited file: python -m tools.calibration)")
    return p


def lookup(design_key: str) -> fp.EcuParams | None:
    """The committed calibration for these design inputs, or None (no data set, or
    ``SUSPENSION_NO_DATA``)."""
    if not enabled():
        return None
    path = _index().get(design_key)
    return _read(path) if path is not None else None


def read(path: Path) -> dict:
    """A data file's header and its calibration (``params``), for the check."""
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    doc["params"] = decode(doc["params"])
    return doc
