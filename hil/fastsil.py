"""The SIL's lockstep loop on the compiled path (``hil.kernels.silloop``): the same contract
and the same bytes as ``hil.nodes.run_in_process`` for the runs it covers (``eligible``),
over the same node objects, whose state it loads before and writes back after.

Python takes over at the events of a plain SIL run (its calendar): every ``CHUNK`` ticks the
sensors' noise for the next block is drawn (the same stream as ``hil.sensors.SensorSuite``'s
blocks of 256), and at ``run_in_process``'s progress ticks progress is shown; each time the
trace hash takes the rows hashed since, ``on_frame`` sees the frames in bus order and the
driver's requests join the app's log. A fault campaign's injector, a driver policy of Python
(a script, a person), the C parity record, a run without SecOC or a node that already ran
take ``hil.nodes.run_in_process`` instead.
"""

from __future__ import annotations

import hashlib
import math
from typing import Callable, Optional

import numpy as np

from firmware.layout import view
from hil import secoc
from hil.kernels import bus as kb
from hil.kernels import frames as kf
from hil.kernels import secoc as ks
from hil.kernels import silloop as kl
from hil.nodes import ID, REQ_KINDS, AppNode, EcuNode, PlantNode

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
    if plant.inject is not None or app.inject is not None:
        return "a fault campaign's injector"
    if app.policy not in kl.POLICIES:
        return f"the driver policy {app.policy!r}"
    if any(cb is not None for cb in (app.on_request, app.on_faults, app.on_recommend)):
        return "the driver app's callbacks"
    if not ecu_node.E[0]["secured"] or plant.cmd_auth is None or app.req_sec is None:
        return "a run without SecOC"
    if not (ecu_node.key_sha == _sha(plant.cmd_auth.mac.key) == _sha(app.req_sec.mac.key)):
        return "nodes with different SecOC keys"
    if ecu_node.state.log is not None:
        return "the fixed-point path's C parity record"
    if not ecu_node.lockstep or ecu_node.uds is not None:
        return "a realtime or diagnosed ECU node"
    if plant.k or ecu_node.k or app.n_status or ecu_node.pending:
        return "nodes that already ran"
    return None


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


def _sil_state(plant: PlantNode, app: AppNode, log_on: bool) -> np.ndarray:
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
    z.policy = kl.POLICIES.index(app.policy)
    z.app_mode, z.reaction, z.app_p_status = app.mode, app.reaction_ticks, app.p_status
    z.kind, z.rmode, z.rid = app.kind, app.req_mode, app.req_id
    z.shown, z.shown_since, z.answered = app._shown, app._shown_since, app._answered
    z.log_on = log_on
    return za


def _plant_receiver(plant: PlantNode) -> np.ndarray:
    """The plant's receiver of ACTUATOR_CMD (its own spec: COUNTER and CHECKSUM checked)."""
    rx, st = kf.rx_table(1), plant.cmd_rx
    kf.supervise(rx[0], plant.codec.specs[ID["ACTUATOR_CMD"]])
    r = rx[0]
    r["valid"], r["good_run"], r["faults"] = st.valid, st.good_run, st.faults
    r["last_counter"], r["last_rx_tick"] = st.last_counter, st.last_rx_tick
    return rx


def _secoc(codec, plant: PlantNode, app: AppNode) -> np.ndarray:
    """The plant's verifier of ACTUATOR_CMD and the app's signer of DRIVER_REQUEST."""
    sec = kf.table(ks.SEC, 4)
    for s, name, fv, rejected in ((kb.S_CMD_RX, "ACTUATOR_CMD", plant.cmd_auth.latest,
                                   plant.cmd_auth.rejected),
                                  (kb.S_REQ_TX, "DRIVER_REQUEST", app.req_sec.fv, 0)):
        lay = secoc.layout(codec, name)
        sec[s] = (lay.fv_byte, lay.mac_byte, fv, rejected)
    return sec


def run(plant: PlantNode, ecu_node: EcuNode, app: AppNode,
        on_frame: Optional[Callable[[int, bytes], None]] = None,
        progress: Optional[Callable[[int, int], None]] = None) -> dict[str, int]:
    """``hil.nodes.run_in_process`` on the compiled loop (``eligible`` must hold)."""
    why = eligible(plant, ecu_node, app)
    if why is not None:
        raise ValueError(f"the compiled SIL loop does not cover {why}")
    codec = plant.codec
    M, F, fault_bits = codec.bus_tables()
    prx, sec = _plant_receiver(plant), _secoc(codec, plant, app)
    za = _sil_state(plant, app, on_frame is not None)
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
    e = ecu_node
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
        status = kl.run(za, e.E, M, F, fault_bits, e.RX, prx, e.SEC, sec, e.crypto, a._phis,
                        a._flows, x, a._pp, a._v, a._acc, plant.zf, speed, true_grade, segment,
                        noise, sup_noise, sens._std, sens._min, sens._lsb, sens._full, st.P,
                        st.T, st.S, st.I, st.O, plant.obs, rows, hashbuf, e.ff, e.ff_first,
                        reqlog, log_id, log_dlc, log_data, k1)
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
    _put_back(z, x, rows, prx, sec, plant, ecu_node, app)
    if status != kl.OK:
        raise RuntimeError(f"lockstep broken at tick {plant.k}")
    return {name: int(z.seen[kb.MESSAGES.index(name)]) for name in _BUS_ORDER
            if z.seen[kb.MESSAGES.index(name)]}


def _put_back(z, x, rows, prx, sec, plant, ecu_node, app) -> None:
    """The nodes' state after the loop, as ``run_in_process`` leaves it (the ECU node's lives
    in its own records, which the loop ran on)."""
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
    plant.fallback_ticks = int(z.fallback_ticks)     # (missed_cmds: none, or lockstep broke)
    plant.auth_failures, plant.auth_failures_booked = int(z.auth_failures), int(z.auth_booked)
    for node in (plant, app):
        for name in _OWN[node.name]:
            i = kb.MESSAGES.index(name)
            if z.sent[i]:
                node.tx.sent[name] += int(z.sent[i])
                node.tx.counters[name] = int(z.ctr[i])   # (Tx keeps one for every message)
    st, row = plant.cmd_rx, prx[0]
    st.valid, st.good_run = bool(row["valid"]), int(row["good_run"])
    st.last_counter, st.last_rx_tick = int(row["last_counter"]), int(row["last_rx_tick"])
    st.faults = int(row["faults"])
    plant.cmd_auth.latest = int(sec[kb.S_CMD_RX]["fv"])
    plant.cmd_auth.rejected = int(sec[kb.S_CMD_RX]["rejected"])
    app.req_sec.fv = int(sec[kb.S_REQ_TX]["fv"])
    ecu_node.rows.frombytes(rows[:ecu_node.k].tobytes())
    app.n_status, app.t = int(z.n_status), int(z.t)
    app.kind, app.req_mode, app.req_id = int(z.kind), int(z.rmode), int(z.rid)
    app._shown, app._shown_since, app._answered = int(z.shown), int(z.shown_since), \
        int(z.answered)
    app._chosen = bool(z.chosen)
