"""DBC codec on cantools, with the project's rounding and the firmware's frame validity.

Encoding rounds physical values to raw integers half away from zero and saturates at the
signal's raw range (cantools' own scaling rounds to even and may raise or wrap: cantools
#635/#462), then packs the raw values with cantools and seals COUNTER and CHECKSUM with
``firmware.safety``. Decoding checks DLC and CHECKSUM with ``firmware.safety`` before it
unpacks; it never raises on bad input.
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


def to_raw(sig, value: float) -> int:
    """Physical -> raw: round half away from zero, saturate, never wrap. NaN -> 0."""
    lo, hi = raw_range(sig)
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, float) and math.isnan(value):
        return 0
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

    def message(self, name: str):
        return self.db.get_message_by_name(name)

    def encode(self, name: str, values: Mapping[str, float], counter: int = 0) -> bytes:
        m = self.message(name)
        raw = {}
        for sig in m.signals:
            if sig.name in ("COUNTER", "CHECKSUM"):
                raw[sig.name] = 0
            else:
                raw[sig.name] = to_raw(sig, values.get(sig.name, 0.0))
        data = m.encode(raw, scaling=False, strict=False)
        return safety.seal(self.specs[m.frame_id], data, counter)

    def decode(self, frame_id: int, data: bytes, state: Optional[safety.RxState] = None,
               tick: int = 0) -> Decoded:
        """Decode with validity checks. Unknown IDs, wrong DLC and bad CHECKSUM give ok=False
        and fault bits, never an exception."""
        spec = self.specs.get(frame_id)
        if spec is None:
            return Decoded("", {}, False, safety.FAULT_UNKNOWN_ID)
        st = state if state is not None else safety.RxState()
        if state is None:
            st.last_counter = -1   # a one-off decode does not judge the counter
        ok = safety.check_frame(spec, st, data, tick)
        m = self.db.get_message_by_frame_id(frame_id)
        if not ok:
            return Decoded(m.name, {}, False, st.faults)
        try:
            values = m.decode(bytes(data), decode_choices=False, scaling=True)
        except Exception:  # noqa: BLE001 - a frame that passed DLC/CRC but does not unpack
            return Decoded(m.name, {}, False, safety.FAULT_DLC)
        return Decoded(m.name, dict(values), True, 0)
