"""DBC codec on cantools, with the project's rounding and the firmware's frame validity.

Encoding rounds physical values to raw integers half away from zero and saturates at the
signal's raw range (cantools' own scaling rounds to even and may raise or wrap: cantools
#635/#462), then packs the raw values with cantools and seals COUNTER and CHECKSUM with
``firmware.safety``. Decoding checks DLC and CHECKSUM with ``firmware.safety`` before it
unpacks, then every signal against the DBC's declared [minimum, maximum] (RANGE); it never
raises on bad input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional

import cantools

from firmware import safety
from firmware.actuator import round_half_away

DBC_PATH = Path(__file__).resolve().parents[1] / "dbc" / "suspension.dbc"


def raw_range(sig) -> tuple[int, int]:
    if sig.is_signed:
        return -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    return 0, (1 << sig.length) - 1


def declared_raw_range(sig) -> tuple[int, int]:
    """The DBC's [minimum, maximum] of a signal as raw integers (the raw range when absent)."""
    lo, hi = raw_range(sig)
    if sig.minimum is not None:
        lo = max(lo, math.ceil((sig.minimum - sig.offset) / sig.scale - 1e-9))
    if sig.maximum is not None:
        hi = min(hi, math.floor((sig.maximum - sig.offset) / sig.scale + 1e-9))
    return lo, hi


def to_raw(sig, value: float) -> int:
    """Physical -> raw: round half away from zero, saturate at the declared range, never
    wrap. NaN -> 0 (or the nearest end of the declared range)."""
    lo, hi = declared_raw_range(sig)
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, float) and math.isnan(value):
        return min(hi, max(lo, 0))
    if isinstance(value, float) and math.isinf(value):
        return hi if value > 0 else lo
    raw = (value - sig.offset) / sig.scale
    if raw >= hi:
        return hi
    if raw <= lo:
        return lo
    return min(hi, max(lo, round_half_away(raw)))


@dataclass
class Decoded:
    name: str
    signals: dict
    ok: bool
    faults: int


class Codec:
    def __init__(self, path: Path = DBC_PATH):
        self.db = cantools.database.load_file(str(path))
        self.specs: dict[int, safety.FrameSpec] = {}
        for m in self.db.messages:
            names = {s.name: s for s in m.signals}
            counter = names.get("COUNTER")
            checksum = names.get("CHECKSUM")
            self.specs[m.frame_id] = safety.FrameSpec(
                msg_id=m.frame_id, dlc=m.length,
                counter_bit=counter.start if counter is not None else None,
                checksum_byte=checksum.start // 8 if checksum is not None else None)
        # bit layouts for the fast path (all signals little-endian, as in our DBC); a DBC
        # with big-endian signals goes through cantools' own packer
        self._layouts: dict[int, Optional[tuple]] = {}
        self._by_name = {m.name: m for m in self.db.messages}
        self._by_id = {m.frame_id: m for m in self.db.messages}
        for m in self.db.messages:
            if all(sig.byte_order == "little_endian" for sig in m.signals):
                self._layouts[m.frame_id] = tuple(
                    (sig.name, sig.start, sig.length, sig.is_signed, *raw_range(sig),
                     sig.scale, sig.offset) for sig in m.signals)
            else:
                self._layouts[m.frame_id] = None
        # signals whose declared range is narrower than their raw range: (name, lo, hi) raw
        self._ranges: dict[int, tuple] = {
            m.frame_id: tuple((sig.name, *declared_raw_range(sig)) for sig in m.signals
                              if declared_raw_range(sig) != raw_range(sig))
            for m in self.db.messages}

    def message(self, name: str):
        return self._by_name[name]

    def cycle_ms(self, name: str) -> int:
        """The message's GenMsgCycleTime from the DBC (0: not cyclic)."""
        return int(self.message(name).cycle_time or 0)

    def encode(self, name: str, values: Mapping[str, float], counter: int = 0) -> bytes:
        """Encode physical values (round half away from zero, saturate), seal COUNTER and
        CHECKSUM."""
        m = self.message(name)
        raw = {sig.name: to_raw(sig, values.get(sig.name, 0.0)) for sig in m.signals
               if sig.name not in ("COUNTER", "CHECKSUM")}
        return self.encode_raw(name, raw, counter)

    def encode_raw(self, name: str, raw_values: Mapping[str, int], counter: int = 0) -> bytes:
        """Encode raw (unscaled) integers, saturating at each signal's raw range."""
        m = self.message(name)
        layout = self._layouts[m.frame_id]
        if layout is None:
            raw = {}
            for sig in m.signals:
                lo, hi = raw_range(sig)
                v = 0 if sig.name in ("COUNTER", "CHECKSUM") else int(raw_values.get(sig.name, 0))
                raw[sig.name] = min(hi, max(lo, v))
            data = m.encode(raw, scaling=False, strict=False)
            return safety.seal(self.specs[m.frame_id], data, counter)
        word = 0
        get = raw_values.get
        for sig, start, length, _signed, lo, hi, _s, _o in layout:
            v = int(get(sig, 0))
            v = hi if v > hi else lo if v < lo else v
            word |= (v & ((1 << length) - 1)) << start
        return safety.seal_word(self.specs[m.frame_id], word, m.length, counter)

    def decode(self, frame_id: int, data: bytes, state: Optional[safety.RxState] = None,
               tick: int = 0, scaling: bool = True,
               spec: Optional[safety.FrameSpec] = None) -> Decoded:
        """Decode with validity checks. Unknown IDs, wrong DLC, bad CHECKSUM and values outside
        the declared range give ok=False and fault bits, never an exception. ``scaling=False``
        gives raw integers; ``spec`` overrides the receiver's view of the message (timeouts,
        rate supervision)."""
        if spec is None:
            spec = self.specs.get(frame_id)
        if spec is None:
            return Decoded("", {}, False, safety.FAULT_UNKNOWN_ID)
        st = state if state is not None else safety.RxState()
        if state is None:
            st.last_counter = -1   # a one-off decode does not judge the counter
        ok = safety.check_frame(spec, st, data, tick)
        m = self._by_id[frame_id]
        if not ok:
            return Decoded(m.name, {}, False, st.faults)
        layout = self._layouts[frame_id]
        if layout is not None:
            word = int.from_bytes(bytes(data), "little")
            raw = {}
            for sig, start, length, signed, _lo, _hi, _scale, _offset in layout:
                v = (word >> start) & ((1 << length) - 1)
                if signed and v >> (length - 1):
                    v -= 1 << length
                raw[sig] = v
        else:
            try:
                raw = dict(m.decode(bytes(data), decode_choices=False, scaling=False))
            except Exception:  # noqa: BLE001 - a frame that passed DLC/CRC but does not unpack
                return Decoded(m.name, {}, False, safety.FAULT_DLC)
        for sig, lo, hi in self._ranges[frame_id]:
            if not lo <= raw[sig] <= hi:
                safety.invalidate(st, safety.FAULT_RANGE)
                return Decoded(m.name, {}, False, st.faults)
        if not scaling:
            return Decoded(m.name, raw, True, 0)
        if layout is not None:
            return Decoded(m.name, {sig: raw[sig] * scale + offset
                                    for sig, *_, scale, offset in layout}, True, 0)
        return Decoded(m.name, dict(m.decode(bytes(data), decode_choices=False)), True, 0)
