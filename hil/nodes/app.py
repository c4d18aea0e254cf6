"""The driver-app node: answers the ECU's recommendations by a policy, a script or a person."""

from __future__ import annotations

from collections import Counter, deque
from typing import Callable, Iterable, Optional


from firmware import params as fp
from firmware.modes import REASON_NONE
from hil.nodes.base import ID, Frame, Tx, period_ticks
from hil.transport import secoc
from hil.transport.codec import Codec, fault_word

REQ_KINDS = {"none": fp.REQ_NONE, "accept": fp.REQ_ACCEPT, "refuse": fp.REQ_REFUSE,
             "choose": fp.REQ_CHOOSE}
POLICIES = ("auto", "fixed", "refuse", "script", "interactive", "web")
QUEUED = ("interactive", "web")       # the policies that send what a person chose


class AppNode:
    """The driver-app emulator. Time is the ECU's: 10 ms per ECU_STATUS received. Answers every
    MODE_RECOMMEND with one DRIVER_REQUEST (a new request, or the heartbeat repeating the last).

    Policies: ``auto`` accepts a recommendation once it has been shown unchanged for the
    reaction delay; ``fixed`` chooses ``mode`` at start, then refuses every recommendation;
    ``refuse`` refuses every recommendation; ``script`` sends timed choices
    [(t_s, kind, mode or None), ...] (``accept`` with no mode accepts what is recommended then);
    ``interactive`` and ``web`` send what :meth:`push` queued (keys in a terminal, clicks
    on the page of ``hil.apps.webapp``)."""

    name = "APP"

    def __init__(self, codec: Codec, policy: str = "auto", *, mode: int = fp.MODE_PASSIVE,
                 reaction_ticks: int = 1000, script: Optional[Iterable] = None,
                 dt: float = 0.001, inject=None, key: Optional[bytes] = None):
        if policy not in POLICIES:
            raise ValueError(f"unknown driver policy {policy!r} (one of {', '.join(POLICIES)})")
        self.codec, self.policy, self.mode, self.dt = codec, policy, mode, dt
        self.reaction_ticks = reaction_ticks
        self.script = deque(sorted(script or [], key=lambda e: e[0]))
        self.tx = Tx(codec)
        # the frames on_frame does nothing with (a bus harness may skip them)
        self.ignore = frozenset(ID.values()) - {ID[n] for n in (
            "ECU_STATUS", "VEHICLE_SPEED", "MODE_RECOMMEND", "ENERGY_STATUS")}
        self.p_status = period_ticks(codec, "ECU_STATUS", dt)
        self.n_status = 0
        self.t = 0                           # ticks of simulated time (from ECU_STATUS)
        self.kind, self.req_mode, self.req_id = fp.REQ_NONE, 0, 0
        self._shown, self._shown_since, self._answered = -1, 0, -1
        self._chosen = False
        self.queued: deque = deque()         # interactive choices (kind, mode)
        self.view: dict = {}                 # latest decoded status for a display
        self.log: list[tuple[float, str, int]] = []   # (t_s, kind, mode) of requests sent
        self.on_request: Optional[Callable[[float, str, int], None]] = None
        # what the driver is told: (tick, FAULTS, REASON) of ECU_STATUS, on each change
        self.faults_seen: list[tuple[int, int, int]] = []
        self.on_faults: Optional[Callable[[float, int, int], None]] = None
        # what the ECU recommends, told on each change: (t_s, recommended, active)
        self.on_recommend: Optional[Callable[[float, int, int], None]] = None
        self._told = None
        self.inject = inject                 # hil.faults.injector.Injector (fault campaign) or None
        self.req_sec = secoc.sender(codec, key, "DRIVER_REQUEST")

    def push(self, kind: str, mode: Optional[int] = None) -> None:
        self.queued.append((kind, mode))

    def script_due(self) -> bool:
        """The script's next entry is due (it goes with the next MODE_RECOMMEND)."""
        return bool(self.script) and self.script[0][0] <= self.t * self.dt + 1e-9

    def request(self, kind: int, mode: int) -> None:
        """Send a DRIVER_REQUEST of ``kind`` for ``mode`` with the next answer."""
        self.kind, self.req_mode = kind, mode
        self.req_id = (self.req_id + 1) & 0xF
        name = next(k for k, v in REQ_KINDS.items() if v == kind)
        self.log.append((self.t * self.dt, name, mode))
        if self.on_request is not None:
            self.on_request(self.t * self.dt, name, mode)

    def _decide(self, rec: int, active: int, reason: int = REASON_NONE) -> None:
        t = self.t
        if self.policy == "fixed" and not self._chosen:
            self._chosen = True
            self.request(fp.REQ_CHOOSE, self.mode)
            return
        if self.policy == "script":
            while self.script_due():
                _, kind, mode = self.script.popleft()
                self.request(REQ_KINDS[kind], rec if mode is None else mode)
            return
        if self.policy in QUEUED:
            if self.queued:
                kind, mode = self.queued.popleft()
                self.request(REQ_KINDS[kind], rec if mode is None else mode)
            return
        if rec != self._shown:
            self._shown, self._shown_since = rec, t
        if reason != REASON_NONE:
            # the ECU overrides the driver's mode (road holding, a fault): the active mode is
            # not the driver's, so a recommendation that differs from it asks nothing of the
            # driver (accepting or refusing it again would be a second request in a few ticks)
            return
        if (rec != active and rec != self._answered
                and t - self._shown_since >= self.reaction_ticks):
            self._answered = rec
            self.request(fp.REQ_ACCEPT if self.policy == "auto" else fp.REQ_REFUSE, rec)
        if rec == active:
            self._answered = -1

    def on_frame(self, fid: int, data: bytes) -> list[Frame]:
        if fid == ID["ECU_STATUS"]:
            d = self.codec.decode(fid, data)
            self.n_status += 1
            self.t = (self.n_status - 1) * self.p_status
            if d.ok:
                self.view.update(d.signals)
                seen = (fault_word(d.signals), int(d.signals["REASON"]))
                if seen != (self.faults_seen[-1][1:] if self.faults_seen else (0, 0)):
                    self.faults_seen.append((self.t, *seen))
                    if self.on_faults is not None:
                        self.on_faults(self.t * self.dt, *seen)
        elif fid in (ID["VEHICLE_SPEED"], ID["ENERGY_STATUS"]):
            d = self.codec.decode(fid, data)
            if d.ok:
                self.view.update(d.signals)
        elif fid == ID["MODE_RECOMMEND"]:
            d = self.codec.decode(fid, data, scaling=False)
            if d.ok:
                s = d.signals
                self.view.update({f"REC_{k}": v for k, v in s.items()})
                rec = (int(s["RECOMMENDED_MODE"]), int(s["ACTIVE_MODE"]))
                if rec != self._told and self.on_recommend is not None:
                    self._told = rec
                    self.on_recommend(self.t * self.dt, *rec)
                self._decide(*rec, int(s["REASON"]))
                if self.inject is not None:
                    self.inject.before_answer(self)
            fid, data = self.tx.frame("DRIVER_REQUEST", {
                "REQ_KIND": self.kind, "REQ_MODE": self.req_mode, "REQ_ID": self.req_id})
            return [(fid, self.req_sec.protect(data) if self.req_sec is not None else data)]
        return []

    def summary(self) -> dict:
        kinds = Counter(k for _, k, _ in self.log)
        out = {"node": "app", "policy": self.policy, "frames_sent": dict(self.tx.sent),
               "requests": dict(kinds), "log": [list(e) for e in self.log],
               "faults_seen": [list(e) for e in self.faults_seen]}
        if self.inject is not None:
            out["injected"] = self.inject.applied
        return out
