"""The ECU's tick compiled (issue 37): the firmware's stages as numba functions over records
with named fields (``layout``: the calibration image, the state, a tick's inputs and
outputs), one call per tick (``ecu.tick``), the same bits as the Python ECU of
``firmware.ecu`` operation for operation, and the same source run by the interpreter with
``NUMBA_DISABLE_JIT=1``.

``Ecu`` is the handle the bench holds: ``step(Inputs) -> Outputs`` (``firmware.ecu``'s
records), the diagnostic memory for the UDS server (``diag``), an ECU reset.

While the port goes on, ``firmware.ecu`` and the stage modules it calls stay as the
reference the compiled tick is checked against, tick by tick (``tests/test_tick.py``).
"""

from __future__ import annotations

import numpy as np

from firmware.ecu import Inputs, Outputs
from firmware.fx.state import TickIn
from firmware.kernels import INTERPRETED
from firmware.params import EcuParams
from firmware.tick import ecu
from firmware.tick.diag import DiagView
from firmware.tick.layout import params_record, view


def _counts(c) -> int:
    """An input's counts as the record holds them: -1 where the Python ADC finds no valid
    sample (None, not an int, a bool, or an int beyond any channel's range)."""
    if isinstance(c, int) and not isinstance(c, bool) and 0 <= c < 1 << 31:
        return c
    return -1


class Ecu:
    """One ECU: calibration ``params``, the fixed-point path with ``tables`` (its
    ``FxTables``; None: float). ``record``: keep the fixed-point path's per-tick hand-over
    and integers (``log``: ``(firmware.fx.state.TickIn, outputs)`` per tick, the C parity
    trace)."""

    def __init__(self, params: EcuParams, tables=None, record: bool = False):
        self.params, self.tables = params, tables
        self.P = params_record(params)
        self.T = params_record(tables) if tables is not None else None
        self.arithmetic = "float" if tables is None else "fixed"
        self.log = [] if record and tables is not None else None
        self.I, self.O = ecu.inputs(), ecu.outputs()
        self._new_state()

    def _new_state(self) -> None:
        self.S = ecu.init(self.params, self.P, self.T)
        self.rec = view(self.S)
        self.diag = DiagView(self.S)

    def __getattr__(self, name):
        """The state's stages as attributes (``ecu.modes.active_mode``, ``ecu.akf.x``:
        numpy records, read and written through)."""
        if name in ("S", "rec") or name.startswith("__"):
            raise AttributeError(name)
        try:
            return getattr(self.rec, name)
        except AttributeError:
            raise AttributeError(f"Ecu has no attribute {name!r}") from None

    def step(self, inp: Inputs) -> Outputs:
        values = ecu.tick_values(
            self.P, self.T, self.S, self.I, self.O, inp.tick, _counts(inp.body_accel),
            _counts(inp.wheel_accel), _counts(inp.susp_defl), _counts(inp.motor_current),
            _counts(inp.speed), _counts(inp.supply), inp.req_kind, inp.req_mode,
            inp.req_counter, inp.link_faults)
        if INTERPRETED:       # (numpy's scalars, where numba returns Python's)
            values = tuple(bool(v) if isinstance(v, np.bool_) else int(v) for v in values)
        out = Outputs(*values)
        if self.log is not None:
            self.log.append(self.fx_tick())
        return out

    def fx_tick(self) -> tuple:
        """The fixed-point path's last tick as the C parity trace takes it: its inputs
        (``TickIn``) and ``firmware.fx.state.outputs``."""
        f = self.S[0]["fx"]
        counts = tuple(None if c < 0 else int(c) for c in f["counts"])
        tin = TickIn(counts, tuple(int(v) for v in f["k_q"]), tuple(int(v) for v in f["r_q"]),
                     int(f["want"]), bool(f["passive"]), bool(f["fault"]), bool(f["regen"]),
                     bool(f["reset"]))
        return tin, (int(f["duty"]), int(f["force"]), *(int(v) for v in f["x"]),
                     *(int(v) for v in f["resid"]), int(f["integ"]), int(f["voltage"]))

    def reset(self) -> None:
        """ECU reset (UDS 0x11): the control state starts again, the DTC memory stays
        (non-volatile) and a new operation cycle begins."""
        kept = self.S[0]["dtc"].copy()
        self._new_state()
        self.S[0]["dtc"] = kept
        ecu.new_cycle(self.S)

    @property
    def tick(self) -> int:
        return int(self.S[0]["tick"])

    @property
    def guard_hits(self) -> int:
        """How often the R-hat guard acted (since the filter last started)."""
        return int(self.S[0]["akf"]["guard_hits"])

    @property
    def gain_saturations(self) -> int:
        return int(self.S[0]["fx"]["gain_saturations"])

    @property
    def x(self) -> np.ndarray:
        """The state estimate [zs', zt', zs, zt, zf] (a view: written through)."""
        return self.S[0]["akf"]["x"]
