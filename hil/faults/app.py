"""Faults of the driver app: requests too often, a mode that does not exist. Harmless to the
drive: the ECU names them and keeps its mode."""

from __future__ import annotations

from dataclasses import dataclass

from firmware import params as fp
from hil.faults.base import Fault, Window, memo


@dataclass(frozen=True, kw_only=True)
class RequestSpam(Fault):
    """A new mode request with every answer; the first asks for the mode in use."""
    node: str = "app"
    safety: bool = False

    def before_answer(self, inj, app, w: Window) -> None:
        m = memo(inj, self)
        i = m["i"] = m.get("i", -1) + 1
        app.request(fp.REQ_CHOOSE, fp.MODE_COMFORT if i % 2 == 0 else fp.MODE_COMPREHENSIVE)
        inj.mark(self.name, app.t)


@dataclass(frozen=True, kw_only=True)
class InvalidRequest(Fault):
    """The app chooses ``mode`` (none such), once."""
    node: str = "app"
    safety: bool = False
    mode: int = 6

    def before_answer(self, inj, app, w: Window) -> None:
        if self.name not in inj.applied:
            app.request(fp.REQ_CHOOSE, self.mode)
            inj.mark(self.name, app.t)
