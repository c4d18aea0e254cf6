"""The three nodes in one process: the lockstep protocol over a FIFO, and a node's warm-up."""

from __future__ import annotations

import copy
import hashlib
from collections import Counter, deque
from typing import Callable, Optional


from hil.nodes.app import AppNode
from hil.nodes.base import MISSING, Tx, message_name
from hil.nodes.ecu import EcuNode
from hil.nodes.plant import PlantNode

def run_in_process(plant: PlantNode, ecu_node: EcuNode, app: AppNode,
                   on_frame: Optional[Callable[[int, bytes], None]] = None,
                   progress: Optional[Callable[[int, int], None]] = None,
                   until: Optional[int] = None) -> dict[str, int]:
    """The lockstep protocol with the three nodes in this process: a FIFO stands in for the
    bus (every frame goes to every other node, in the order sent), up to tick ``until`` (the
    route's end by default). Returns the frames that crossed the FIFO, per message name."""
    nodes = (plant, ecu_node, app)
    queue: deque = deque()
    routes: dict = {}     # (sender, frame ID) -> the nodes that do not ignore it
    seen: Counter = Counter()

    def send(sender, frames):
        queue.extend((sender, f) for f in frames)
        while queue:
            src, (fid, data) = queue.popleft()
            seen[fid] += 1
            if on_frame is not None:
                on_frame(fid, data)
            dests = routes.get((src, fid))
            if dests is None:
                dests = routes[src, fid] = tuple(
                    n for n in nodes if n is not src and fid not in getattr(n, "ignore", ()))
            for node in dests:
                replies = node.on_frame(fid, data)
                if replies:
                    queue.extend((node, r) for r in replies)

    report_every = max(1, plant.n // 200)
    end = plant.n if until is None else min(plant.n, until)
    while plant.k < end:
        send(plant, plant.emit())
        while ecu_node.ready():
            send(ecu_node, ecu_node.tick())
            ecu_node.record()
        if not plant.ready():
            raise RuntimeError(f"lockstep broken at tick {plant.k}")
        plant.step()
        if progress is not None and (plant.k % report_every == 0 or plant.done):
            progress(plant.k, plant.n)
    return {message_name(fid): n for fid, n in seen.items()}


def warm_up(node, ticks: int = 30) -> None:
    """Run the node's code paths a few times on a throwaway copy before the real run: numba
    loads a kernel from its cache (or compiles it) on its first call, 0.2 s for the first one
    in a process, and Python's first pass through a path is slower; in realtime pacing both
    would be missed deadlines at the start. The plant copy steps with an enabled command; the
    ECU copy gets valid sensor and speed frames and one tick without a sensor frame (its
    compiled tick, ``firmware``, is one function: the first call loads all of it). The
    node itself is untouched (the same bytes on the bus afterwards)."""
    shared = {id(node.codec): node.codec}
    if hasattr(node, "params"):             # the calibration: the same arrays (and layouts)
        shared[id(node.params)] = node.params
    for rec in (getattr(getattr(node, "state", None), name, None) for name in ("P", "T")):
        if rec is not None:                 # (its records: read-only, a copy is not)
            shared[id(rec)] = rec
    if getattr(node, "inject", None) is not None:
        shared[id(node.inject)] = node.inject
    if getattr(node, "mac", None) is not None:     # (a CMAC context does not copy; its
        shared[id(node.mac)] = node.mac            # callers' freshness is in their tables)
    if hasattr(node, "sha"):
        shared[id(node.sha)] = hashlib.sha256()   # (a hash object does not copy)
    w = copy.deepcopy(node, shared)
    if isinstance(w, PlantNode):
        w.inject = None
        for k in range(min(ticks, w.n)):
            w.emit()
            w.cmd, w.cmd_tick, w.cmd_fresh = (1000 * (k % 3 - 1), k % 2 == 0, True), w.k, True
            w.step()
    elif isinstance(w, EcuNode):
        tx = Tx(w.codec)
        for k in range(ticks):
            if k % 10 == 0:
                w.on_frame(*tx.frame_phys("VEHICLE_SPEED", {"SPEED": 20.0}))
            w.on_frame(*tx.frame("PLANT_SENSORS", {
                "BODY_ACCEL_RAW": 2048 + k, "WHEEL_ACCEL_RAW": 2048 - k, "SUSP_DEFL_RAW": 2048,
                "MOTOR_CURRENT_RAW": 2048}))
            while w.ready():
                w.tick()
                w.record()
        w.pending.append(MISSING)
        w.tick()
        w.record()      # (the tick is one compiled function: every controller came with it)
