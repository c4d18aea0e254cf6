"""DBC codec on cantools, with the project's rounding and the firmware's frame validity.

Encoding rounds physical values to raw integers half away from zero and saturates at the
signal's raw range (cantools' own scaling rounds to even and may raise or wrap: cantools
#635/#462), packs the raw values from cantools' signal layout (worked out once per message: a
plan) and seals COUNTER and CHECKSUM with ``firmware.safety``. Every signal is little-endian
(docs/architecture.md, Conventions); a DBC with a big-endian signal is refused when it is
loaded. Decoding checks DLC and CHECKSUM with ``firmware.safety`` before it unpacks, then every signal against the DBC's declared [minimum, maximum] (RANGE); it never
raises on bad input.
"""

from __future__ import annotations

import dataclasses

import math
from pathlib import Path
from typing import Callable, Mapping, NamedTuple, Optional

import cantools

from calib.errors import ConfigError
from firmware import safety
from firmware.fixedpoint import round_half_away

DBC_PATH = Path(__file__).resolve().parents[2] / "dbc" / "suspension.dbc"

# The ECU's fault word on the bus: ECU_STATUS has one signal per bit of firmware.safety's word,
# FAULT_<NAME> (named so that every decoder shows the fault by name, with a value table).
FAULT_SIGNALS = {bit: "FAULT_" + name.upper() for bit, name in safety.FAULT_NAMES.items()}


def fault_signals(word: int) -> dict[str, int]:
    """ECU_STATUS's fault signals of a fault word."""
    return {sig: 1 if word & bit else 0 for bit, sig in FAULT_SIGNALS.items()}


def fault_word(signals: Mapping[str, float]) -> int:
    """The fault word of decoded ECU_STATUS signals."""
    return sum(bit for bit, sig in FAULT_SIGNALS.items() if signals.get(sig))


def raw_range(sig) -> tuple[int, int]:
    if sig.is_signed:
        return -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    return 0, (1 << sig.length) - 1


def declared_raw_range(sig) -> tuple[int, int]:
    """The DBC's [minimum, maximum] of a signal as raw integers (the raw range when absent)."""
    lo, hi = raw_range(sig)
    if sig.minimum is not None:
        lo = max(lo, math.ceil(_snap((sig.minimum - sig.offset) / sig.scale)))
    if sig.maximum is not None:
        hi = min(hi, math.floor(_snap((sig.maximum - sig.offset) / sig.scale)))
    return lo, hi


def _snap(raw: float) -> float:
    """A raw limit computed in floating point, on the integer it is within rounding of
    (relative: 2147483.647 / 0.001 is 2147483646.9999998)."""
    n = round(raw)
    return float(n) if abs(raw - n) <= 1e-9 * max(1.0, abs(raw)) else raw


def to_raw(sig, value: float) -> int:
    """Physical -> raw: round half away from zero, saturate at the declared range, never
    wrap. NaN -> 0 (or the nearest end of the declared range)."""
    return _to_raw(value, *declared_raw_range(sig), sig.offset, sig.scale)


def _to_raw(value: float, lo: int, hi: int, offset: float, scale: float) -> int:
    """``to_raw`` with the signal's declared raw range, offset and scale given."""
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, float):
        value = float(value)     # (a numpy scalar: Python arithmetic, the same bits)
        if math.isnan(value):
            return min(hi, max(lo, 0))
        if math.isinf(value):
            return hi if value > 0 else lo
    raw = (value - offset) / scale
    if raw >= hi:
        return hi
    if raw <= lo:
        return lo
    return min(hi, max(lo, round_half_away(raw)))


def _pack_word(fields: tuple, values) -> int:
    """The payload as a little-endian integer: each raw value saturated at its signal's raw
    range and shifted to its start bit; ``fields`` are (start bit, mask, lo, hi)."""
    word = 0
    for (start, mask, lo, hi), v in zip(fields, values):
        v = int(v)
        if v > hi:
            v = hi
        elif v < lo:
            v = lo
        word |= (v & mask) << start
    return word


class Decoded(NamedTuple):
    name: str
    signals: dict
    ok: bool
    faults: int


class _Plan(NamedTuple):
    """One message's packing, worked out once from the DBC (little-endian signals only)."""
    name: str
    frame_id: int
    length: int
    spec: safety.FrameSpec
    names: tuple         # the signals to pack (COUNTER/CHECKSUM left out) ...
    pack: tuple          # ... and their (start bit, mask, raw lo, raw hi)
    unpack: tuple        # (signal, start bit, mask, sign bit or 0), every signal
    scaled: tuple        # (signal, scale, offset)


class DbcError(ConfigError, ValueError):
    """A DBC the bench cannot use: one line naming the file and the reason."""


def load_dbc(path: Path):
    try:
        return cantools.database.load_file(str(path))
    except OSError as exc:
        raise DbcError(f"{path}: cannot read the DBC: {exc.strerror or exc}") from None
    except Exception as exc:  # noqa: BLE001 - cantools raises parser-specific errors
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DbcError(f"{path}: not a valid DBC: {first}") from None


class Codec:
    def __init__(self, path: Path = DBC_PATH):
        self.db = load_dbc(path)
        self.specs: dict[int, safety.FrameSpec] = {}
        for m in self.db.messages:
            names = {s.name: s for s in m.signals}
            counter = names.get("COUNTER")
            checksum = names.get("CHECKSUM")
            self.specs[m.frame_id] = safety.FrameSpec(
                msg_id=m.frame_id, dlc=m.length,
                counter_bit=counter.start if counter is not None else None,
                checksum_byte=checksum.start // 8 if checksum is not None else None)
        self._by_name = {m.name: m for m in self.db.messages}
        self._by_id = {m.frame_id: m for m in self.db.messages}
        # the packing of every message, worked out once (every signal little-endian)
        self._plans: dict = {}
        for m in self.db.messages:
            big = [sig.name for sig in m.signals if sig.byte_order != "little_endian"]
            if big:
                raise DbcError(f"{path}: {m.name}.{big[0]} is big-endian; the bench's codec "
                               f"packs little-endian signals only")
            packed = [sig for sig in m.signals if sig.name not in ("COUNTER", "CHECKSUM")]
            plan = _Plan(
                name=m.name, frame_id=m.frame_id, length=m.length,
                spec=self.specs[m.frame_id],
                names=tuple(sig.name for sig in packed),
                pack=tuple((sig.start, (1 << sig.length) - 1, *raw_range(sig))
                           for sig in packed),
                unpack=tuple((sig.name, sig.start, (1 << sig.length) - 1,
                              1 << (sig.length - 1) if sig.is_signed else 0)
                             for sig in m.signals),
                scaled=tuple((sig.name, sig.scale, sig.offset) for sig in m.signals))
            self._plans[m.name] = self._plans[m.frame_id] = plan
        # signals whose declared range is narrower than their raw range: (name, lo, hi) raw
        self._ranges: dict[int, tuple] = {
            m.frame_id: tuple((sig.name, *declared_raw_range(sig)) for sig in m.signals
                              if declared_raw_range(sig) != raw_range(sig))
            for m in self.db.messages}
        # encode(): (signal, (declared raw lo, hi, offset, scale)), COUNTER/CHECKSUM left out
        self._declared = {m.name: tuple((sig.name, (*declared_raw_range(sig), sig.offset,
                                                    sig.scale))
                                        for sig in m.signals
                                        if sig.name not in ("COUNTER", "CHECKSUM"))
                          for m in self.db.messages}

    def message(self, name: str):
        return self._by_name[name]

    def cycle_ms(self, name: str) -> int:
        """The message's GenMsgCycleTime from the DBC (0: not cyclic)."""
        return int(self.message(name).cycle_time or 0)

    def encode(self, name: str, values: Mapping[str, float], counter: int = 0) -> bytes:
        """Encode physical values (round half away from zero, saturate), seal COUNTER and
        CHECKSUM."""
        get = values.get
        raw = {sig: _to_raw(get(sig, 0.0), *conv) for sig, conv in self._declared[name]}
        return self.encode_raw(name, raw, counter)

    def encode_raw(self, name: str, raw_values: Mapping[str, int], counter: int = 0) -> bytes:
        """Encode raw (unscaled) integers, saturating at each signal's raw range."""
        plan = self._plans[name]
        get = raw_values.get
        word = _pack_word(plan.pack, [get(sig, 0) for sig in plan.names])
        return safety.seal_word(plan.spec, word, plan.length, counter)

    def packer(self, name: str, signals: tuple[str, ...],
               checksum: bool = True) -> Callable[..., bytes]:
        """``encode_raw`` for a fixed list of signals given by position (the per-tick frames:
        no dictionary to build and search): ``packer(name, ("A", "B"))((a, b), counter)``
        is ``encode_raw(name, {"A": a, "B": b}, counter)``. ``checksum=False`` leaves the
        CHECKSUM byte 0 for a later step to write (``hil.transport.secoc.Sender.protect`` does)."""
        plan = self._plans[name]
        packable = {sig.name for sig in self.message(name).signals} - {"COUNTER", "CHECKSUM"}
        unknown = set(signals) - packable
        if unknown:
            raise ValueError(f"{name} has no signal(s) {sorted(unknown)} to pack")
        fields = tuple(plan.pack[plan.names.index(sig)] for sig in signals)
        spec, length = plan.spec, plan.length
        if not checksum:
            spec = dataclasses.replace(spec, checksum_byte=None)

        def pack(values, counter: int = 0) -> bytes:
            return safety.seal_word(spec, _pack_word(fields, values), length, counter)
        return pack

    def unpacker(self, name: str, signals: tuple[str, ...]) -> Callable[..., tuple]:
        """``decode(..., scaling=False)`` for a fixed list of signals, returned by position
        (the per-tick frames: no dictionary to build): ``unpacker(name, ("A", "B"))(data,
        state, tick, spec=None)`` gives ``((a, b), 0)`` for a valid frame and ``(None,
        faults)`` otherwise, with the same checks, the same fault bits and the same update
        of ``state`` (an ``RxState``, required) as ``decode``."""
        m = self.message(name)
        plan = self._plans[name]
        unknown = set(signals) - {sig.name for sig in m.signals}
        if unknown:
            raise ValueError(f"{name} has no signal(s) {sorted(unknown)} to unpack")
        fid, own_spec = m.frame_id, self.specs[m.frame_id]
        where = {sig: (start, mask, sign) for sig, start, mask, sign in plan.unpack}
        fields = tuple(where[sig] for sig in signals)
        checks = tuple((*where[sig], lo, hi) for sig, lo, hi in self._ranges[fid])
        check_frame, invalidate, fault_range = safety.check_frame, safety.invalidate, \
            safety.FAULT_RANGE

        def unpack(data, state: safety.RxState, tick: int = 0,
                   spec: Optional[safety.FrameSpec] = None) -> tuple:
            if not check_frame(spec or own_spec, state, data, tick):
                return None, state.faults
            word = int.from_bytes(data, "little")
            for start, mask, sign, lo, hi in checks:
                v = (word >> start) & mask
                if not lo <= (v - (sign << 1) if v & sign else v) <= hi:
                    invalidate(state, fault_range)
                    return None, state.faults
            out = []
            for start, mask, sign in fields:
                v = (word >> start) & mask
                out.append(v - (sign << 1) if v & sign else v)
            return tuple(out), 0
        return unpack

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
        plan = self._plans[frame_id]
        word = int.from_bytes(data, "little")
        raw = {}
        for sig, start, mask, sign in plan.unpack:
            v = (word >> start) & mask
            if v & sign:
                v -= sign << 1
            raw[sig] = v
        for sig, lo, hi in self._ranges[frame_id]:
            if not lo <= raw[sig] <= hi:
                safety.invalidate(st, safety.FAULT_RANGE)
                return Decoded(m.name, {}, False, st.faults)
        if not scaling:
            return Decoded(m.name, raw, True, 0)
        return Decoded(m.name, {sig: raw[sig] * scale + offset
                                for sig, scale, offset in plan.scaled}, True, 0)

    def bus_tables(self):
        """The compiled nodes' tables (``hil.kernels.bus``): (MSG, FIELD, the fault bit of
        each of ECU_STATUS's fault signals), laid out once per codec."""
        if getattr(self, "_bus", None) is None:
            import numpy as np

            from hil.kernels import bus

            uses = bus.USES + tuple(("ECU_STATUS", sig) for sig in FAULT_SIGNALS.values())
            M, F = self.frame_tables(bus.MESSAGES, uses)
            self._bus = (M, F, np.array(list(FAULT_SIGNALS), dtype=np.int64))
        return self._bus

    def frame_tables(self, messages: tuple[str, ...], uses: tuple[tuple[str, str], ...]):
        """The tables of the compiled frames (``hil.kernels.frames``) for ``messages`` (``MSG``
        rows in that order) and the signals ``uses`` (``(message, signal)`` pairs: ``FIELD``
        rows 0 .. len(uses) - 1 in that order; each message's ranged signals, the ones
        ``decode`` checks, follow)."""
        from hil.kernels import frames as kf

        M = kf.table(kf.MSG, len(messages))
        sig_of = {(m.name, s.name): s for m in self.db.messages for s in m.signals}
        unknown = [u for u in uses if u not in sig_of]
        if unknown:
            raise ValueError(f"the DBC has no signal(s) {unknown}")
        rows = [sig_of[u] for u in uses]
        for i, name in enumerate(messages):
            spec = self.specs[self.message(name).frame_id]
            ranged = [sig_of[name, sig] for sig, _, _ in self._ranges[spec.msg_id]]
            crc = safety.CRC8_INIT
            for b in (spec.msg_id & 0xFFFF).to_bytes(2, "little"):
                crc = safety._CRC_TABLE[crc ^ b]
            M[i] = (spec.msg_id, spec.dlc, -1 if spec.counter_bit is None else spec.counter_bit,
                    -1 if spec.checksum_byte is None else spec.checksum_byte, crc, len(rows),
                    len(ranged))
            rows += ranged
        F = kf.table(kf.FIELD, len(rows))
        for j, sig in enumerate(rows):
            F[j] = (sig.start, (1 << sig.length) - 1,
                    1 << (sig.length - 1) if sig.is_signed else 0, *raw_range(sig),
                    *declared_raw_range(sig), sig.scale, sig.offset)
        return M, F
