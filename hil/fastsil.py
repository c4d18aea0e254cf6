"""The SIL's lockstep loop on the compiled path (``hil.kernels.silloop``): the same contract
and the same bytes as ``hil.nodes.run_in_process`` for the runs it covers (``eligible``),
over the same node objects, whose state it loads before and writes back after.

Python takes over at the events of a plain SIL run (its calendar): every ``CHUNK`` ticks the
sensors' noise for the next block is drawn (the same stream as ``hil.sensors.SensorSuite``'s
blocks of 256), and at ``run_in_process``'s progress ticks progress is shown; each time the
trace hash takes the rows hashed since, ``on_frame`` sees the frames in bus order and the
driver's requests join the app's log. A fault campaign's
injector, a driver policy of Python (a script, a person), the C parity record, a run without
SecOC or a node that already ran take ``hil.nodes.run_in_process`` instead.
"""

from __future__ import annotations

from array import array
from collections import Counter
from typing import Callable, Optional

import numpy as np

from hil import secoc
from hil.codec import FAULT_SIGNALS
from hil.kernels import frames as kf
from hil.kernels import secoc as ks
from hil.kernels import silloop as kl
from hil.kernels.cmac import Cmac
from hil.nodes import ID, REQ_KINDS, AppNode, EcuNode, PlantNode
from firmware import safety
from firmware.tick.layout import view

CHUNK = 16384            # ticks between Python's turns (a multiple of the noise block, 256)
_OWN = {"PLANT": ("VEHICLE_SPEED", "PLANT_SUPPLY", "SIM_TRUTH", "ENERGY_STATUS",
                  "PLANT_SENSORS"),
        "ECU": ("ACTUATOR_CMD", "ECU_STATUS", "ECU_ESTIMATES", "MODE_RECOMMEND"),
        "APP": ("DRIVER_REQUEST",)}
# the order in which a run's frames first cross the bus (tick 0): the bus count's order
_BUS_ORDER = ("VEHICLE_SPEED", "PLANT_SUPPLY", "SIM_TRUTH", "ENERGY_STATUS", "PLANT_SENSORS",
              "ECU_STATUS", "ECU_ESTIMATES", "MODE_RECOMMEND", "DRIVER_REQUEST", "ACTUATOR_CMD")
_KIND_NAME = {v: k for k, v in REQ_KINDS.items()}


def eligible(plant: PlantNode, ecu_node: EcuNode, app: AppNode) -> Optional[str]:
    """None when the compiled loop covers this run; else why not (``run_in_process`` runs
    it)."""
    if plant.inject is not None or app.inject is not None:
        return "a fault campaign's injector"
    if app.policy not in kl.POLICIES:
        return f"the driver policy {app.policy!r}"
    if any(cb is not None for cb in (app.on_request, app.on_faults, app.on_recommend)):
        return "the driver app's callbacks"
    if ecu_node.cmd_sec is None or plant.cmd_auth is None or app.req_sec is None:
        return "a run without SecOC"
    if ecu_node.state.log is not None:
        return "the fixed-point path's C parity record"
    if not ecu_node.lockstep or ecu_node.uds is not None:
        return "a realtime or diagnosed ECU node"
    if plant.k or ecu_node.k or app.n_status or ecu_node.pending:
        return "nodes that already ran"
    if plant.noise_step is not None and plant.noise_step[1] is None:
        return "a noise step without a gain"
    return None


def _noise_tick(plant: PlantNode) -> int:
    """The first tick whose ``k * dt >= t`` (``PlantNode.emit``'s noise step); past the end
    without one."""
    if plant.noise_step is None:
        return plant.n + 1
    t = plant.noise_step[0]
    k = max(0, int(t / plant.dt) - 2)
    while k * plant.dt < t:
        k += 1
    return k


def _sil_state(plant: PlantNode, ecu_node: EcuNode, app: AppNode, log_on: bool) -> np.ndarray:
    za = kf.table(kl.SIL, 1)
    z = view(za)
    a = plant.active
    sup = plant.supply.channel
    z.n, z.dt = plant.n, plant.dt
    z.p_speed, z.p_supply, z.p_truth, z.p_energy = (plant.p_speed, plant.p_supply,
                                                    plant.p_truth, plant.p_energy)
    z.cmd_timeout = plant.cmd_timeout_ticks
    z.cmd_duty, z.cmd_regen, z.cmd_enable = plant.cmd
    z.cmd_tick, z.cmd_seq = plant.cmd_tick, plant.cmd_seq
    z.has_actuator, z.track, z.ind_l, z.zf = a.has_actuator, a.track_ledger, a._L, a.zf
    z.noise_k = _noise_tick(plant)
    z.noise_gain = plant.noise_step[1] if plant.noise_step is not None else 1.0
    z.gain[:] = plant.sensors.noise_gain
    z.sup_std, z.sup_min, z.sup_lsb, z.sup_full = (sup.noise_std, sup.range_min, sup.lsb,
                                                   2 ** sup.bits - 1)
    z.speed_raw = z.supply_new = -1
    z.req_kind, z.req_mode, z.req_id = ecu_node.req
    z.seq = ecu_node.seq
    z.last_rec[:] = -1
    z.p_status, z.p_rec = ecu_node.p_status, ecu_node.p_rec
    z.policy = kl.POLICIES.index(app.policy)
    z.app_mode, z.reaction, z.app_p_status = app.mode, app.reaction_ticks, app.p_status
    z.kind, z.rmode, z.rid = app.kind, app.req_mode, app.req_id
    z.shown, z.shown_since, z.answered = app._shown, app._shown_since, app._answered
    z.log_on = log_on
    return za


def _receivers(plant: PlantNode, ecu_node: EcuNode) -> np.ndarray:
    rx = kf.rx_table(5)
    pairs = ((kl.R_SPEED, ecu_node.rx_specs[ID["VEHICLE_SPEED"]], ecu_node.rx[ID["VEHICLE_SPEED"]]),
             (kl.R_SUPPLY, ecu_node.rx_specs[ID["PLANT_SUPPLY"]], ecu_node.rx[ID["PLANT_SUPPLY"]]),
             (kl.R_SENSORS, ecu_node.sensors_spec, ecu_node.rx[ID["PLANT_SENSORS"]]),
             (kl.R_REQ, ecu_node.rx_specs[ID["DRIVER_REQUEST"]],
              ecu_node.rx[ID["DRIVER_REQUEST"]]),
             (kl.R_CMD, plant.codec.specs[ID["ACTUATOR_CMD"]], plant.cmd_rx))
    for r, spec, st in pairs:
        rx[r] = (spec.counter_bit is not None, spec.timeout_ticks, spec.min_interval_ticks,
                 spec.recover_frames, st.valid, st.good_run, st.last_counter, st.last_rx_tick,
                 st.faults)
    return rx


def _put_back_receivers(rx, plant: PlantNode, ecu_node: EcuNode) -> None:
    for r, st in ((kl.R_SPEED, ecu_node.rx[ID["VEHICLE_SPEED"]]),
                  (kl.R_SUPPLY, ecu_node.rx[ID["PLANT_SUPPLY"]]),
                  (kl.R_SENSORS, ecu_node.rx[ID["PLANT_SENSORS"]]),
                  (kl.R_REQ, ecu_node.rx[ID["DRIVER_REQUEST"]]), (kl.R_CMD, plant.cmd_rx)):
        row = rx[r]
        st.valid, st.good_run = bool(row["valid"]), int(row["good_run"])
        st.last_counter, st.last_rx_tick = int(row["last_counter"]), int(row["last_rx_tick"])
        st.faults = int(row["faults"])


def _secoc(codec, plant: PlantNode, ecu_node: EcuNode, app: AppNode) -> np.ndarray:
    sec = kf.table(ks.SEC, 4)
    for s, name, obj in ((kl.S_CMD_TX, "ACTUATOR_CMD", ecu_node.cmd_sec),
                         (kl.S_CMD_RX, "ACTUATOR_CMD", plant.cmd_auth),
                         (kl.S_REQ_TX, "DRIVER_REQUEST", app.req_sec),
                         (kl.S_REQ_RX, "DRIVER_REQUEST", ecu_node.req_auth)):
        lay = secoc.layout(codec, name)
        fv = obj.fv if isinstance(obj, secoc.Sender) else obj.latest
        sec[s] = (lay.fv_byte, lay.mac_byte, fv, getattr(obj, "rejected", 0))
    return sec


def run(plant: PlantNode, ecu_node: EcuNode, app: AppNode,
        on_frame: Optional[Callable[[int, bytes], None]] = None,
        progress: Optional[Callable[[int, int], None]] = None) -> dict[str, int]:
    """``hil.nodes.run_in_process`` on the compiled loop (``eligible`` must hold)."""
    why = eligible(plant, ecu_node, app)
    if why is not None:
        raise ValueError(f"the compiled SIL loop does not cover {why}")
    codec = plant.codec
    uses = kl.USES + tuple(("ECU_STATUS", sig) for sig in FAULT_SIGNALS.values())
    M, F = codec.frame_tables(kl.MESSAGES, uses)
    fault_bits = np.array(list(FAULT_SIGNALS), dtype=np.int64)
    rx, sec = _receivers(plant, ecu_node), _secoc(codec, plant, ecu_node, app)
    key = ecu_node.cmd_sec.mac.key
    if plant.cmd_auth.mac.key != key or app.req_sec.mac.key != key:
        raise ValueError("the compiled SIL loop runs one SecOC key on every node")
    mac = Cmac(key)
    crypto = (mac.ctx, np.zeros(32, np.uint8), mac.tag16, mac.length)
    za = _sil_state(plant, ecu_node, app, on_frame is not None)
    z = view(za)
    a, n = plant.active, plant.n
    x = np.array(a.x, dtype=float)
    # the passive twin only sees the road: the whole drive at once (PlantNode.step's chunks)
    tw = plant.twin.run_passive(plant.zf[1:n + 1])
    for name in ("ba", "sws", "dtd", "vrel"):
        plant.arrays["p_" + name][:n] = tw[name]
    plant.twin_until = n
    sens = plant.sensors
    true_grade = np.ascontiguousarray(plant.true_grade, dtype=np.int64)
    segment = np.ascontiguousarray(plant.timeline.segment, dtype=np.int64)
    speed = np.ascontiguousarray(plant.timeline.speed_mps, dtype=float)
    rows = np.zeros((n, 9), np.int64)
    ff = np.zeros((kl.NMSG, 32), np.int64)
    ff_first = np.zeros((kl.NMSG, 32), np.int64)
    hashbuf = np.zeros(CHUNK * kl.ROW_BYTES, np.uint8)
    reqlog = np.zeros((CHUNK, 3), np.int64)
    cap = CHUNK * kl.FRAMES_PER_TICK if on_frame is not None else 1
    log_id, log_dlc = np.zeros(cap, np.int64), np.zeros(cap, np.int64)
    log_data = np.zeros((cap, 8), np.uint8)
    st = ecu_node.state
    status = kl.OK
    report_every = max(1, n // 200)          # (run_in_process's progress calls)
    noise = sup_noise = None
    while z.k < n and status == kl.OK:
        k0 = int(z.k)
        if noise is None or k0 >= z.noise_base + CHUNK:    # the next block of noise
            noise = sens.rng.standard_normal((CHUNK, 5))
            first = -(-k0 // plant.p_supply) * plant.p_supply
            sup_noise = plant.supply.rng.standard_normal(
                len(range(first, k0 + CHUNK, plant.p_supply)))
            z.noise_base, z.supply_next = k0, 0
        k1 = min(n, int(z.noise_base) + CHUNK)
        if progress is not None:
            k1 = min(k1, (k0 // report_every + 1) * report_every)
        z.nlog, z.hpos, z.nreq = 0, 0, 0
        status = kl.run(za, M, F, fault_bits, rx, sec, crypto, a._phis, a._flows, x, a._pp,
                        a._v, a._acc, plant.zf, speed, true_grade, segment, noise, sup_noise,
                        sens._std, sens._min, sens._lsb, sens._full, st.P, st.T, st.S, st.I,
                        st.O, plant.obs, rows, hashbuf, ff, ff_first, reqlog, log_id, log_dlc,
                        log_data, k1)
        row_bytes = hashbuf[:z.hpos].tobytes()
        ecu_node.sha.update(row_bytes)
        if ecu_node.hashed is not None:
            ecu_node.hashed += row_bytes
        for t, kind, mode in reqlog[:z.nreq].tolist():
            app.log.append((t * app.dt, _KIND_NAME[kind], mode))
        if on_frame is not None:
            for fid, dlc, data in zip(log_id[:z.nlog].tolist(), log_dlc[:z.nlog].tolist(),
                                      log_data[:z.nlog]):
                on_frame(fid, data[:dlc].tobytes())
        if progress is not None and status == kl.OK and (z.k % report_every == 0
                                                         or z.k >= n):
            progress(int(z.k), n)
    _put_back(z, x, rows, ff, ff_first, rx, sec, plant, ecu_node, app)
    if status != kl.OK:
        raise RuntimeError(f"lockstep broken at tick {plant.k}")
    return {name: int(z.seen[kl.MESSAGES.index(name)]) for name in _BUS_ORDER
            if z.seen[kl.MESSAGES.index(name)]}


def _put_back(z, x, rows, ff, ff_first, rx, sec, plant, ecu_node, app) -> None:
    """The nodes' state after the loop, as ``run_in_process`` leaves it."""
    a = plant.active
    a.x, a.zf = x, float(z.zf)
    a.bump_contacts += int(z.bump_contacts)
    a.lift_off_events += int(z.lift_offs)
    a.in_bump_contact, a.tire_lifted = bool(z.in_bump), bool(z.lifted)
    a.current_limited_steps += int(z.limited_steps)
    plant.k = int(z.k)
    plant.cmd = (int(z.cmd_duty), bool(z.cmd_regen), bool(z.cmd_enable))
    plant.cmd_tick, plant.cmd_fresh, plant.cmd_seq = int(z.cmd_tick), bool(z.cmd_fresh), \
        int(z.cmd_seq)
    plant.bad_cmd_frames, plant.stale_cmd_frames = int(z.bad_cmd), int(z.stale_cmd)
    plant.missed_cmds, plant.fallback_ticks = int(z.missed), int(z.fallback_ticks)
    plant.auth_failures, plant.auth_failures_booked = int(z.auth_failures), int(z.auth_booked)
    for node in (plant, ecu_node, app):
        for name in _OWN[node.name]:
            i = kl.MESSAGES.index(name)
            if z.sent[i]:
                node.tx.sent[name] += int(z.sent[i])
                node.tx.counters[name] = int(z.ctr[i])   # (Tx keeps one for every message)
    _put_back_receivers(rx, plant, ecu_node)
    ecu_node.cmd_sec.fv = int(sec[kl.S_CMD_TX]["fv"])
    app.req_sec.fv = int(sec[kl.S_REQ_TX]["fv"])
    for s, rcv in ((kl.S_CMD_RX, plant.cmd_auth), (kl.S_REQ_RX, ecu_node.req_auth)):
        rcv.latest, rcv.rejected = int(sec[s]["fv"]), int(sec[s]["rejected"])
    e = ecu_node
    e.k = int(z.ek)
    e.speed_raw = None if z.speed_raw < 0 else int(z.speed_raw)
    e.supply_new = None if z.supply_new < 0 else int(z.supply_new)
    e.req = (int(z.req_kind), int(z.req_mode), int(z.req_id))
    e.awaiting, e.link_faults, e.seq = int(z.awaiting), int(z.link_faults), int(z.seq)
    e.status_faults = int(z.status_faults)
    if z.last_rec[0] >= 0:
        lr = [int(v) for v in z.last_rec]
        e.last_rec = (lr[0], lr[1], lr[2], bool(lr[3]))
    e.rows = array("q", rows[:e.k].tobytes())
    stamps = sorted((int(ff_first[i, b]), i, b) for i, b in zip(*np.nonzero(ff)))
    for _, i, b in stamps:
        label = safety.FAULT_NAMES.get(1 << int(b), f"bit{b}")
        e.frame_faults[f"{kl.MESSAGES[i]}:{label}"] += int(ff[i, b])
    app.n_status, app.t = int(z.n_status), int(z.t)
    app.kind, app.req_mode, app.req_id = int(z.kind), int(z.rmode), int(z.rid)
    app._shown, app._shown_since, app._answered = int(z.shown), int(z.shown_since), \
        int(z.answered)
    app._chosen = bool(z.chosen)

