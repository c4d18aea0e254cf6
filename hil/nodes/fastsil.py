"""The SIL's lockstep loop on the compiled path (``hil.kernels.silloop``): the same contract
and the same bytes as ``hil.nodes.run_in_process`` for the runs it covers (``eligible``),
over the same node objects, whose state it loads before and writes back after.

The compiled loop runs until the next event of Python's calendar, where Python takes over,
then resumes:
- every ``CHUNK`` ticks the sensors' noise for the next block is drawn (the same stream as
  ``hil.sim.sensors.SensorSuite``'s blocks of 256), and at ``run_in_process``'s progress ticks
  progress is shown; each time the trace hash takes the rows hashed since, ``on_frame`` sees
  the frames in bus order, and the driver's requests and what the driver was told join the
  app's logs;
- in the spans of Python's own (a fault campaign's windows, ``hil.validate.faults.Injector.spans``,
  and the caller's ``python`` spans: a tester's read of the DTC memory) the node objects run
  the ticks (``run_in_process``), from the state the loop wrote back into them; the loop
  loads it again after the span;
- a driver script's entries: Python's app sends them (``calendar``).
The same bytes either way (``tests/test_silloop.py``). The C parity record (the fixed-point
hand-over of every tick) is copied in the loop. A person driving (``interactive``, ``web``),
the app's callbacks, a run without SecOC, or a realtime or diagnosed ECU node take
``hil.nodes.run_in_process`` instead.
"""

from __future__ import annotations

import hashlib
import math
from collections import Counter
from typing import Callable, Iterable, Optional

import numpy as np

from firmware.ecu import fx_entry
from firmware.layout import view
from hil.kernels import bus as kb
from hil.kernels import frames as kf
from hil.kernels import secoc as ks
from hil.kernels import sensors as ks_sensors
from hil.kernels import silloop as kl
from hil.nodes import ECU_TRACE, ID, REQ_KINDS, AppNode, EcuNode, PlantNode, run_in_process
from hil.transport import secoc

CHUNK = 16384            # ticks between Python's turns (a multiple of the noise block, 256)
_OWN = {"PLANT": ("VEHICLE_SPEED", "PLANT_SUPPLY", "SIM_TRUTH", "ENERGY_STATUS",
                  "PLANT_SENSORS"),
        "APP": ("DRIVER_REQUEST",)}
# the order in which a run's frames first cross the bus (tick 0): the bus count's order
_BUS_ORDER = ("VEHICLE_SPEED", "PLANT_SUPPLY", "SIM_TRUTH", "ENERGY_STATUS", "PLANT_SENSORS",
              "ECU_STATUS", "ECU_ESTIMATES", "MODE_RECOMMEND", "DRIVER_REQUEST", "ACTUATOR_CMD")
_KIND_NAME = {v: k for k, v in REQ_KINDS.items()}


def eligible(plant: PlantNode, ecu_node: EcuNode, app: AppNode) -> Optional[str]:
    """None when the compiled loop covers this run; else why not (``run_in_process`` runs
    it)."""
    if app.policy not in kl.POLICIES:
        return f"the driver policy {app.policy!r}"
    if any(cb is not None for cb in (app.on_request, app.on_faults, app.on_recommend)):
        return "the driver app's callbacks"
    if not ecu_node.E[0]["secured"] or plant.cmd_auth is None or app.req_sec is None:
        return "a run without SecOC"
    if not (ecu_node.key_sha == _sha(plant.cmd_auth.mac.key) == _sha(app.req_sec.mac.key)):
        return "nodes with different SecOC keys"
    if not ecu_node.lockstep or ecu_node.uds is not None:
        return "a realtime or diagnosed ECU node"
    if not _between_ticks(plant, ecu_node):
        return "nodes in the middle of a tick"
    return None


def _between_ticks(plant: PlantNode, ecu_node: EcuNode) -> bool:
    """The nodes stand between two lockstep ticks (where the loop can take them over)."""
    return (not plant.cmd_fresh and not ecu_node.pending and ecu_node.held_cmd is None
            and not ecu_node.unrecorded and ecu_node.k == plant.k)


def _no_fault() -> np.ndarray:
    f = kf.table(ks_sensors.FAULT, 1)
    f["channel"] = -1
    return f


def _sha(key: bytes) -> str:
    return hashlib.sha256(key).hexdigest()


def _noise_tick(plant: PlantNode) -> int:
    """The first tick whose ``k * dt >= t`` (``PlantNode.emit``'s noise step); past the end
    without one."""
    if plant.noise_step is None:
        return plant.n + 1
    t = float(plant.noise_step[0])
    if not t < math.inf:                    # (NaN or +inf: never, as k * dt >= t says)
        return plant.n + 1
    if t <= 0.0:
        return 0
    k = max(0, int(t / plant.dt) - 2)
    while k * plant.dt < t:
        k += 1
    return k


def calendar(plant: PlantNode, ecu_node: EcuNode, app: AppNode,
             python: Iterable[tuple[int, int]] = ()) -> list[tuple[int, int]]:
    """The spans [start, end) of ticks Python runs, merged and sorted: the injectors',
    ``python``'s, and a driver script's (from the tick of an entry's time to past the next
    MODE_RECOMMEND, where the app sends it; ``_python_owes`` runs on if that comes later)."""
    spans = [*python, *(s for node in (plant, app) if node.inject is not None
                        for s in node.inject.spans())]
    if app.policy == "script":
        e = ecu_node.E[0]
        after = int(e["p_rec"]) + int(e["p_status"]) + 2
        for t_s, *_ in app.script:
            if math.isfinite(t_s):
                k = max(0, int(t_s / plant.dt) - 1)
                spans.append((k, k + after))
    spans.sort()
    out: list[list[int]] = []
    for a, b in spans:
        if b <= a:
            continue
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def _python_owes(plant: PlantNode, ecu_node: EcuNode, app: AppNode) -> bool:
    """Python runs on past its span: the nodes are in the middle of a tick, or a script's
    entry is due (it goes with the next MODE_RECOMMEND: ``AppNode._decide``'s test)."""
    if plant.done:
        return False
    return not _between_ticks(plant, ecu_node) or (app.policy == "script"
                                                    and app.script_due())


class _Loop:
    """The compiled loop's state over one run: the SIL record, the tables, the per-tick
    outputs and the buffers Python empties after each call."""

    def __init__(self, plant: PlantNode, ecu_node: EcuNode, app: AppNode,
                 on_frame: Optional[Callable[[int, bytes], None]]):
        self.plant, self.ecu_node, self.app, self.on_frame = plant, ecu_node, app, on_frame
        codec = plant.codec
        self.M, self.F, self.fault_bits = codec.bus_tables()
        za = kf.table(kl.SIL, 1)
        self.za, self.z = za, view(za)
        z = self.z
        sup = plant.supply.channel
        z.n, z.dt = plant.n, plant.dt
        z.p_speed, z.p_supply, z.p_truth, z.p_energy = (plant.p_speed, plant.p_supply,
                                                        plant.p_truth, plant.p_energy)
        z.cmd_timeout = plant.cmd_timeout_ticks
        a = plant.active
        z.has_actuator, z.track, z.ind_l = a.has_actuator, a.track_ledger, a._L
        z.noise_k = _noise_tick(plant)
        z.noise_gain = plant.noise_step[1] if plant.noise_step is not None else 1.0
        z.sup_std, z.sup_min, z.sup_lsb, z.sup_full = (sup.noise_std, sup.range_min, sup.lsb,
                                                       2 ** sup.bits - 1)
        z.policy = kl.POLICIES.index(app.policy)
        z.app_mode, z.reaction, z.app_p_status = app.mode, app.reaction_ticks, app.p_status
        z.log_on = on_frame is not None
        z.wire = plant.inject is not None
        self.prx = kf.rx_table(2)
        for r in self.prx:
            kf.supervise(r, codec.specs[ID["ACTUATOR_CMD"]])
        self.sec = kf.table(ks.SEC, kl.S_CMD_WIRE + 1)
        lay = secoc.layout(codec, "ACTUATOR_CMD")
        for s in (kb.S_CMD_RX, kl.S_CMD_WIRE):
            self.sec[s]["fv_byte"], self.sec[s]["mac_byte"] = lay.fv_byte, lay.mac_byte
        lay = secoc.layout(codec, "DRIVER_REQUEST")
        self.sec[kb.S_REQ_TX]["fv_byte"], self.sec[kb.S_REQ_TX]["mac_byte"] = (lay.fv_byte,
                                                                              lay.mac_byte)
        n = plant.n
        self.x = np.zeros(len(a.x))
        self.true_grade = np.ascontiguousarray(plant.true_grade, dtype=np.int64)
        self.segment = np.ascontiguousarray(plant.timeline.segment, dtype=np.int64)
        self.speed = np.ascontiguousarray(plant.timeline.speed_mps, dtype=float)
        self.rows = np.zeros((n, len(ECU_TRACE)), np.int64)
        self.hashbuf = np.zeros(CHUNK * kl.ROW_BYTES, np.uint8)
        self.reqlog = np.zeros((CHUNK, 3), np.int64)
        self.fslog = np.zeros((CHUNK, 3), np.int64)
        cap = CHUNK * kl.FRAMES_PER_TICK if on_frame is not None else 1
        self.log_id, self.log_dlc = np.zeros(cap, np.int64), np.zeros(cap, np.int64)
        self.log_data = np.zeros((cap, 8), np.uint8)
        # the C parity record: the state's fixed-point hand-over, copied per tick as bytes
        st = ecu_node.state
        self.s_bytes = st.S.view(np.uint8)
        fx = st.S.dtype.fields["fx"]
        z.fx_on, z.fx_off = st.log is not None, fx[1]
        self.fx_rows = np.zeros((n if st.log is not None else 1, fx[0].itemsize), np.uint8)
        self.fx_type = fx[0]
        self.noise = self.sup_noise = self.sup_state = None
        self.seen: Counter = Counter()
        # the plant's sensor fault (its stuck count is written in place), else none
        self.sensor_fault = plant.sensors.fault if plant.sensors.fault is not None \
            else _no_fault()

    # -- the nodes' state in, and back -------------------------------------------------------

    def load(self) -> None:
        """The state of the node objects into the loop's (the ECU node's lives in its own
        records, which the loop runs on)."""
        plant, app, z = self.plant, self.app, self.z
        a = plant.active
        z.k, z.zf, z.in_bump, z.lifted = plant.k, a.zf, a.in_bump_contact, a.tire_lifted
        self.x[:] = a.x
        z.cmd_duty, z.cmd_regen, z.cmd_enable = plant.cmd
        z.cmd_tick, z.cmd_seq, z.cmd_fresh = plant.cmd_tick, plant.cmd_seq, plant.cmd_fresh
        z.bad_cmd, z.stale_cmd = plant.bad_cmd_frames, plant.stale_cmd_frames
        z.fallback_ticks = plant.fallback_ticks
        z.auth_failures, z.auth_booked = plant.auth_failures, plant.auth_failures_booked
        z.bump_contacts = z.lift_offs = z.limited_steps = 0         # (added when put back)
        z.gain[:] = plant.sensors.noise_gain
        for node in (plant, app):
            for name in _OWN[node.name]:
                i = kb.MESSAGES.index(name)
                z.ctr[i], z.sent[i] = node.tx.counters.get(name, 0), 0
        z.seen[:] = 0
        z.n_status, z.t, z.chosen = app.n_status, app.t, app._chosen
        z.kind, z.rmode, z.rid = app.kind, app.req_mode, app.req_id
        z.shown, z.shown_since, z.answered = app._shown, app._shown_since, app._answered
        z.fs_word, z.fs_reason = app.faults_seen[-1][1:] if app.faults_seen else (0, 0)
        for row, st in ((0, plant.cmd_rx), (kl.R_WIRE, plant.cmd_rx_wire)):
            r = self.prx[row]
            r["valid"], r["good_run"], r["faults"] = st.valid, st.good_run, st.faults
            r["last_counter"], r["last_rx_tick"] = st.last_counter, st.last_rx_tick
        for s, auth in ((kb.S_CMD_RX, plant.cmd_auth), (kl.S_CMD_WIRE, plant.cmd_auth_wire)):
            self.sec[s]["fv"], self.sec[s]["rejected"] = auth.latest, auth.rejected
        self.sec[kb.S_REQ_TX]["fv"], self.sec[kb.S_REQ_TX]["rejected"] = app.req_sec.fv, 0
        self.ek0 = self.ecu_node.k
        # the sensors' noise: what is left of their block, else a new one at the next turn
        sens = plant.sensors
        left = sens._noise[sens._next:]
        self.noise = np.array(left) if len(left) else None
        z.noise_base = plant.k
        if self.noise is not None:
            self._draw_supply(plant.k, len(self.noise))

    def _draw_supply(self, k0: int, ticks: int) -> None:
        """The supply channel's noise for its samples in ticks [k0, k0 + ticks) (where its
        generator stood kept: ``put_back`` leaves it after the samples used)."""
        plant = self.plant
        rng = plant.supply.rng
        self.sup_state = rng.bit_generator.state
        first = -(-k0 // plant.p_supply) * plant.p_supply
        self.sup_noise = rng.standard_normal(len(range(first, k0 + ticks, plant.p_supply)))
        self.z.supply_next = 0

    def put_back(self) -> None:
        """The loop's state into the node objects, as ``run_in_process`` leaves it."""
        z, plant, ecu_node, app = self.z, self.plant, self.ecu_node, self.app
        a = plant.active
        a.x, a.zf = self.x.copy(), float(z.zf)
        a.bump_contacts += int(z.bump_contacts)
        a.lift_off_events += int(z.lift_offs)
        a.in_bump_contact, a.tire_lifted = bool(z.in_bump), bool(z.lifted)
        a.current_limited_steps += int(z.limited_steps)
        plant.k = int(z.k)
        plant.cmd = (int(z.cmd_duty), bool(z.cmd_regen), bool(z.cmd_enable))
        plant.cmd_tick, plant.cmd_fresh, plant.cmd_seq = int(z.cmd_tick), bool(z.cmd_fresh), \
            int(z.cmd_seq)
        plant.bad_cmd_frames, plant.stale_cmd_frames = int(z.bad_cmd), int(z.stale_cmd)
        plant.fallback_ticks = int(z.fallback_ticks)  # (missed_cmds: none, or lockstep broke)
        plant.auth_failures, plant.auth_failures_booked = int(z.auth_failures), \
            int(z.auth_booked)
        plant.sensors.noise_gain[:] = z.gain
        for node in (plant, app):
            for name in _OWN[node.name]:
                i = kb.MESSAGES.index(name)
                if z.sent[i]:
                    node.tx.sent[name] += int(z.sent[i])
                    node.tx.counters[name] = int(z.ctr[i])   # (Tx keeps one for every message)
        for row, st in ((0, plant.cmd_rx), (kl.R_WIRE, plant.cmd_rx_wire)):
            r = self.prx[row]
            st.valid, st.good_run = bool(r["valid"]), int(r["good_run"])
            st.last_counter, st.last_rx_tick = int(r["last_counter"]), int(r["last_rx_tick"])
            st.faults = int(r["faults"])
        for s, auth in ((kb.S_CMD_RX, plant.cmd_auth), (kl.S_CMD_WIRE, plant.cmd_auth_wire)):
            auth.latest, auth.rejected = int(self.sec[s]["fv"]), int(self.sec[s]["rejected"])
        app.req_sec.fv = int(self.sec[kb.S_REQ_TX]["fv"])
        ecu_node.rows.frombytes(self.rows[self.ek0:ecu_node.k].tobytes())
        st = ecu_node.state
        if st.log is not None:
            records = self.fx_rows[self.ek0:ecu_node.k].copy().view(self.fx_type)[:, 0]
            st.log += [fx_entry(f) for f in records]
        app.n_status, app.t = int(z.n_status), int(z.t)
        app.kind, app.req_mode, app.req_id = int(z.kind), int(z.rmode), int(z.rid)
        app._shown, app._shown_since, app._answered = int(z.shown), int(z.shown_since), \
            int(z.answered)
        app._chosen = bool(z.chosen)
        for i, name in enumerate(kb.MESSAGES):
            if z.seen[i]:
                self.seen[name] += int(z.seen[i])
        # the noise not used: the sensors' block from here on, the supply's generator put
        # back to where it stood after the samples used
        sens = plant.sensors
        if self.noise is not None:
            sens._noise, sens._next = self.noise[plant.k - int(z.noise_base):], 0
            rng = plant.supply.rng
            rng.bit_generator.state = self.sup_state
            rng.standard_normal(int(z.supply_next))
        self.noise = None

    # -- running -----------------------------------------------------------------------------

    def run(self, k_end: int, progress: Optional[Callable[[int, int], None]]) -> None:
        """The loop from the nodes' tick up to ``k_end``."""
        plant, e, app, z = self.plant, self.ecu_node, self.app, self.z
        a, n, sens, st = plant.active, plant.n, plant.sensors, e.state
        self.load()
        status = kl.OK
        report_every = max(1, n // 200)          # (run_in_process's progress calls)
        end = min(n, k_end)
        while z.k < end and status == kl.OK:
            k0 = int(z.k)
            if self.noise is None or k0 >= z.noise_base + len(self.noise):   # the next block
                self.noise = sens.rng.standard_normal((CHUNK, 5))
                z.noise_base = k0
                self._draw_supply(k0, CHUNK)
            k1 = min(end, int(z.noise_base) + len(self.noise))
            if progress is not None:
                k1 = min(k1, (k0 // report_every + 1) * report_every)
            z.nlog, z.hpos, z.nreq, z.nfs = 0, 0, 0, 0
            status = kl.run(self.za, e.E, self.M, self.F, self.fault_bits, e.RX, self.prx,
                            e.SEC, self.sec, e.crypto, a._phis, a._flows, self.x, a._pp, a._v,
                            a._acc, plant.zf, self.speed, self.true_grade, self.segment,
                            self.noise, self.sup_noise, sens._std, sens._min, sens._lsb,
                            sens._full, self.sensor_fault, st.P, st.T, st.S, st.I, st.O, plant.obs, self.rows,
                            self.hashbuf, e.ff, e.ff_first, self.reqlog, self.fslog,
                            self.log_id, self.log_dlc, self.log_data, self.s_bytes,
                            self.fx_rows, k1)
            self._drain()
            if progress is not None and status == kl.OK and (z.k % report_every == 0
                                                             or z.k >= n):
                progress(int(z.k), n)
        self.put_back()
        if status != kl.OK:
            raise RuntimeError(f"lockstep broken at tick {plant.k}")

    def _drain(self) -> None:
        """The buffers of one call: the hashed rows, the driver's requests and what it was
        told, the frames."""
        z, e, app = self.z, self.ecu_node, self.app
        row_bytes = self.hashbuf[:z.hpos].tobytes()
        e.sha.update(row_bytes)
        if e.hashed is not None:
            e.hashed += row_bytes
        for t, kind, mode in self.reqlog[:z.nreq].tolist():
            app.log.append((t * app.dt, _KIND_NAME[kind], mode))
        app.faults_seen += [tuple(r) for r in self.fslog[:z.nfs].tolist()]
        if self.on_frame is not None:
            for fid, dlc, data in zip(self.log_id[:z.nlog].tolist(),
                                      self.log_dlc[:z.nlog].tolist(), self.log_data[:z.nlog]):
                self.on_frame(fid, data[:dlc].tobytes())


def run(plant: PlantNode, ecu_node: EcuNode, app: AppNode,
        on_frame: Optional[Callable[[int, bytes], None]] = None,
        progress: Optional[Callable[[int, int], None]] = None,
        python: Iterable[tuple[int, int]] = ()) -> dict[str, int]:
    """``hil.nodes.run_in_process`` on the compiled loop (``eligible`` must hold), Python
    running the node objects in the spans of ``calendar`` (the injectors' and ``python``'s,
    [start, end) in ticks)."""
    why = eligible(plant, ecu_node, app)
    if why is not None:
        raise ValueError(f"the compiled SIL loop does not cover {why}")
    n = plant.n
    # the passive twin only sees the road: the rest of the drive at once (PlantNode.step's
    # chunks)
    k = plant.twin_until
    if k < n:
        tw = plant.twin.run_passive(plant.zf[k + 1:n + 1])
        for name in ("ba", "sws", "dtd", "vrel"):
            plant.arrays["p_" + name][k:n] = tw[name]
        plant.twin_until = n
    loop = _Loop(plant, ecu_node, app, on_frame)
    seen: Counter = Counter()
    for a, b in [*calendar(plant, ecu_node, app, python), (n, n)]:
        if plant.k < a:
            loop.run(a, progress)
            seen.update(loop.seen)
            loop.seen = Counter()
        until = b
        while plant.k < until:
            seen.update(run_in_process(plant, ecu_node, app, on_frame, progress, until=until))
            if _python_owes(plant, ecu_node, app):
                until = plant.k + 1
    # in the order a run's frames first cross the bus (tick 0), then the rest as first seen
    order = [*_BUS_ORDER, *(m for m in seen if m not in _BUS_ORDER)]
    return {name: seen[name] for name in order if seen[name]}
