"""The SIL's lockstep loop compiled (issue 37): the plant, ECU and driver-app nodes of
``hil.nodes`` and the bus between them as one numba function that runs tick after tick until
the next event for Python (the end of a chunk: its buffers drained, the sensors' noise drawn,
progress shown), the same frames in the same order as ``hil.nodes.run_in_process`` and the
same bytes (``tests/test_silloop.py`` holds the two together; ``hil.nodes`` stays the
reference and the path of every run this loop does not cover: ``hil.fastsil.eligible``).

Per tick k, as ``hil.nodes``' docstring tells the protocol: the plant samples its sensors and
sends VEHICLE_SPEED, PLANT_SUPPLY, SIM_TRUTH (every 10 ms), ENERGY_STATUS (100 ms) and
PLANT_SENSORS; the ECU ticks (``firmware.tick.ecu.tick``) and sends ECU_STATUS and
ECU_ESTIMATES (10 ms) and MODE_RECOMMEND (100 ms and on change), the app answers that with a
DRIVER_REQUEST, then the ECU's (signed) ACTUATOR_CMD goes to the plant, which steps.

State: one record ``Z`` (``SIL``'s fields: each node's scalars, its transmit COUNTERs, the
frames sent and seen per message); the frame tables of ``hil.kernels.frames`` (messages in
``MESSAGES``' order, signals in ``USES``' order), the receivers (``R_*``) and the SecOC rows
(``S_*``); the plant's arrays (``hil.plant.QuarterCarPlant``'s); the ECU's records
(``firmware.tick``); the per-tick outputs (the plant's observations, the ECU's trace rows,
the hashed rows, the frame log, the driver's requests).
"""

from __future__ import annotations

import numpy as np

from firmware import params as fp
from firmware.kernels import njit
from firmware.modes import REASON_NONE
from firmware.safety import FAULT_AUTH
from firmware.tick import ecu
from hil.kernels import frames as kf
from hil.kernels import plant as kp
from hil.kernels import secoc as ks
from hil.kernels.sensors import quantise_into

MESSAGES = ("VEHICLE_SPEED", "PLANT_SUPPLY", "SIM_TRUTH", "ENERGY_STATUS", "PLANT_SENSORS",
            "ACTUATOR_CMD", "ECU_STATUS", "ECU_ESTIMATES", "MODE_RECOMMEND", "DRIVER_REQUEST")
(M_SPEED, M_SUPPLY, M_TRUTH, M_ENERGY, M_SENSORS, M_CMD, M_STATUS, M_EST, M_REC,
 M_REQ) = range(len(MESSAGES))
USES = (("VEHICLE_SPEED", "SPEED"), ("PLANT_SUPPLY", "SUPPLY_VOLTAGE_RAW"),
        ("SIM_TRUTH", "TRUE_ROAD"), ("SIM_TRUTH", "TRUE_DTD"), ("SIM_TRUTH", "TRUE_SWS"),
        ("SIM_TRUTH", "TRUE_GRADE"), ("SIM_TRUTH", "SEGMENT"),
        ("ENERGY_STATUS", "STORED_ENERGY"), ("ENERGY_STATUS", "SUPPLY_ENERGY"),
        ("PLANT_SENSORS", "BODY_ACCEL_RAW"), ("PLANT_SENSORS", "WHEEL_ACCEL_RAW"),
        ("PLANT_SENSORS", "SUSP_DEFL_RAW"), ("PLANT_SENSORS", "MOTOR_CURRENT_RAW"),
        ("ACTUATOR_CMD", "DUTY"), ("ACTUATOR_CMD", "REGEN"), ("ACTUATOR_CMD", "ENABLE"),
        ("ACTUATOR_CMD", "SENSOR_SEQ"),
        ("ECU_STATUS", "ACTIVE_MODE"), ("ECU_STATUS", "ESTIMATED_GRADE"),
        ("ECU_STATUS", "REASON"), ("ECU_STATUS", "BA_RMS"), ("ECU_STATUS", "DTD_RMS"),
        ("ECU_ESTIMATES", "ROAD_EST"), ("ECU_ESTIMATES", "DTD_EST"),
        ("ECU_ESTIMATES", "GQ_LOG"), ("ECU_ESTIMATES", "FORCE_CMD"),
        ("MODE_RECOMMEND", "RECOMMENDED_MODE"), ("MODE_RECOMMEND", "ESTIMATED_GRADE"),
        ("MODE_RECOMMEND", "ACTIVE_MODE"), ("MODE_RECOMMEND", "REASON"),
        ("MODE_RECOMMEND", "OVERRIDE"),
        ("DRIVER_REQUEST", "REQ_KIND"), ("DRIVER_REQUEST", "REQ_MODE"),
        ("DRIVER_REQUEST", "REQ_ID"))
(U_SPEED, U_SUPPLY, U_TRUE_ROAD, U_TRUE_DTD, U_TRUE_SWS, U_TRUE_GRADE, U_SEGMENT, U_STORED,
 U_DRAWN, U_SENS, _, _, _, U_DUTY, U_REGEN, U_ENABLE, U_SEQ, U_ST_ACTIVE, U_ST_GRADE,
 U_ST_REASON, U_ST_BA, U_ST_DTD, U_ROAD_EST, U_DTD_EST, U_GQ, U_FORCE, U_REC, U_REC_GRADE,
 U_REC_ACTIVE, U_REC_REASON, U_REC_OVERRIDE, U_KIND, U_MODE, U_ID) = range(len(USES))
# then ECU_STATUS's fault signals, one per bit of the fault word (``FAULT_BITS`` gives the bits)
U_FAULTS = len(USES)

R_SPEED, R_SUPPLY, R_SENSORS, R_REQ, R_CMD = range(5)    # the ECU's four receivers, the plant's
S_CMD_TX, S_CMD_RX, S_REQ_TX, S_REQ_RX = range(4)        # SecOC: ECU -> plant, app -> ECU
POLICIES = ("auto", "fixed", "refuse")                   # the driver policies compiled here
NMSG = len(MESSAGES)
ROW_BYTES = 93           # a hashed row (hil.nodes.HASHED, little-endian, no padding)
FRAMES_PER_TICK = 12     # at most, for the frame log's size
UNKNOWN_GRADE_ON_BUS = 7
OK, LOCKSTEP_BROKEN = 0, 1
N_OBS = len(kp.OBS)      # the plant's observations, then the duty applied, fallback, rejected

SIL = np.dtype([
    # the plant node
    ("k", "i8"), ("n", "i8"), ("dt", "f8"), ("p_speed", "i8"), ("p_supply", "i8"),
    ("p_truth", "i8"), ("p_energy", "i8"), ("cmd_timeout", "i8"), ("cmd_duty", "i8"),
    ("cmd_regen", "i8"), ("cmd_enable", "i8"), ("cmd_tick", "i8"), ("cmd_fresh", "i8"),
    ("cmd_seq", "i8"), ("bad_cmd", "i8"), ("stale_cmd", "i8"), ("missed", "i8"),
    ("fallback_ticks", "i8"), ("auth_failures", "i8"), ("auth_booked", "i8"),
    ("has_actuator", "i8"), ("track", "i8"), ("ind_l", "f8"), ("zf", "f8"),
    ("in_bump", "i8"), ("lifted", "i8"), ("bump_contacts", "i8"), ("lift_offs", "i8"),
    ("limited_steps", "i8"), ("noise_k", "i8"), ("noise_gain", "f8"), ("gain", "f8", (5,)),
    ("noise_base", "i8"), ("supply_next", "i8"), ("sup_std", "f8"), ("sup_min", "f8"),
    ("sup_lsb", "f8"), ("sup_full", "i8"),
    # the ECU node
    ("ek", "i8"), ("speed_raw", "i8"), ("supply_new", "i8"), ("req_kind", "i8"),
    ("req_mode", "i8"), ("req_id", "i8"), ("awaiting", "i8"), ("held", "i8"),
    ("link_faults", "i8"), ("seq", "i8"), ("status_faults", "i8"), ("last_rec", "i8", (4,)),
    ("p_status", "i8"), ("p_rec", "i8"), ("pending", "i8"), ("counts", "i8", (4,)),
    ("ff_stamp", "i8"),
    # the driver app
    ("policy", "i8"), ("app_mode", "i8"), ("reaction", "i8"), ("n_status", "i8"),
    ("t", "i8"), ("kind", "i8"), ("rmode", "i8"), ("rid", "i8"), ("shown", "i8"),
    ("shown_since", "i8"), ("answered", "i8"), ("chosen", "i8"), ("app_p_status", "i8"),
    # the bus: COUNTERs, frames sent and seen per message; the buffers' fill
    ("ctr", "i8", (NMSG,)), ("sent", "i8", (NMSG,)), ("seen", "i8", (NMSG,)),
    ("log_on", "i8"), ("nlog", "i8"), ("hpos", "i8"), ("nreq", "i8")])


@njit
def _log(Z, mi, m, buf, log_id, log_dlc, log_data) -> None:
    """A frame crossed the bus: counted, and kept for the log."""
    Z.seen[mi] += 1
    if Z.log_on:
        j = Z.nlog
        log_id[j] = m.id
        log_dlc[j] = m.dlc
        for i in range(m.dlc):
            log_data[j, i] = buf[i]
        Z.nlog = j + 1


@njit
def _note(Z, ff, ff_first, mi, faults) -> None:
    """``EcuNode._note``: the link faults of the tick, counted per message and fault bit (the
    first time each is seen stamped, for the report's order)."""
    Z.link_faults |= faults
    for b in range(32):
        if faults & (1 << b):
            if ff[mi, b] == 0:
                ff_first[mi, b] = Z.ff_stamp
                Z.ff_stamp += 1
            ff[mi, b] += 1


@njit
def _wr(buf, pos, v, nbytes):
    for i in range(nbytes):
        buf[pos + i] = (v >> (8 * i)) & 0xFF
    return pos + nbytes


@njit
def _record(Z, o, inp, speed, supply, link, rows, hashbuf) -> None:
    """``EcuNode.record``: the hashed row (``hil.nodes.HASHED``) and the trace row."""
    k = inp.tick
    p = _wr(hashbuf, Z.hpos, k, 8)
    for c in range(4):
        p = _wr(hashbuf, p, inp.counts[c], 4)
    p = _wr(hashbuf, p, speed, 4)
    p = _wr(hashbuf, p, supply, 4)
    p = _wr(hashbuf, p, inp.req_kind, 4)
    p = _wr(hashbuf, p, inp.req_mode, 4)
    p = _wr(hashbuf, p, inp.req_counter, 4)
    p = _wr(hashbuf, p, link, 4)
    p = _wr(hashbuf, p, o.duty_q15, 4)
    p = _wr(hashbuf, p, o.regen, 1)
    p = _wr(hashbuf, p, o.enable, 1)
    p = _wr(hashbuf, p, o.recommended_mode, 1)
    p = _wr(hashbuf, p, o.active_mode, 1)
    p = _wr(hashbuf, p, o.grade, 1)
    p = _wr(hashbuf, p, o.reason, 1)
    p = _wr(hashbuf, p, o.faults, 4)
    p = _wr(hashbuf, p, o.events, 1)
    p = _wr(hashbuf, p, o.override, 1)
    p = _wr(hashbuf, p, 0, 1)
    p = _wr(hashbuf, p, o.force_cmd_n, 4)
    p = _wr(hashbuf, p, o.road_est_um, 4)
    p = _wr(hashbuf, p, o.dtd_est_um, 4)
    p = _wr(hashbuf, p, o.gq_est_log_c, 4)
    p = _wr(hashbuf, p, o.ba_rms_mmps2, 4)
    p = _wr(hashbuf, p, o.dtd_rms_um, 4)
    p = _wr(hashbuf, p, 0, 4)
    Z.hpos = p
    r = rows[k]
    r[0], r[1], r[2], r[3], r[4] = (o.road_est_um, o.dtd_est_um, o.force_cmd_n, o.grade,
                                    o.active_mode)
    r[5], r[6], r[7], r[8] = o.recommended_mode, o.faults, o.enable, o.reason


@njit
def _app_send(Z, kind, mode, reqlog) -> None:
    """``AppNode._send``: a new request (logged with its time in ticks)."""
    Z.kind = kind
    Z.rmode = mode
    Z.rid = (Z.rid + 1) & 0xF
    j = Z.nreq
    reqlog[j, 0], reqlog[j, 1], reqlog[j, 2] = Z.t, kind, mode
    Z.nreq = j + 1


@njit
def _app_decide(Z, rec, active, reason, reqlog) -> None:
    """``AppNode._decide`` for the policies ``auto``, ``fixed`` and ``refuse``."""
    t = Z.t
    if Z.policy == 1 and Z.chosen == 0:
        Z.chosen = 1
        _app_send(Z, fp.REQ_CHOOSE, Z.app_mode, reqlog)
        return
    if rec != Z.shown:
        Z.shown = rec
        Z.shown_since = t
    if reason != REASON_NONE:
        return
    if rec != active and rec != Z.answered and t - Z.shown_since >= Z.reaction:
        Z.answered = rec
        _app_send(Z, fp.REQ_ACCEPT if Z.policy == 0 else fp.REQ_REFUSE, rec, reqlog)
    if rec == active:
        Z.answered = -1


@njit
def _plant_cmd(Z, M, F, RX, SEC, buf, crypto) -> None:
    """``PlantNode._receive_cmd`` (no fault campaign): SecOC first, then the frame checks; a
    valid command is applied, and ends the tick if it answers this tick's sensor frame."""
    m = M[M_CMD]
    ctx, msg, tag16, length = crypto
    if ks.forged(m, SEC[S_CMD_RX], buf, m.dlc, ctx, msg, tag16, length):
        Z.auth_failures += 1
        return
    if not kf.receive(F, m, RX[R_CMD], buf, m.dlc, Z.k):
        Z.bad_cmd += 1
        return
    w = kf.load(buf, m.dlc)
    Z.cmd_duty = kf.get(w, F[U_DUTY])
    Z.cmd_regen = kf.get(w, F[U_REGEN])
    Z.cmd_enable = kf.get(w, F[U_ENABLE])
    Z.cmd_seq = kf.get(w, F[U_SEQ])
    Z.cmd_tick = Z.k
    if Z.cmd_seq == ((Z.ctr[M_SENSORS] - 1) & 0x3):
        Z.cmd_fresh = 1
    else:
        Z.stale_cmd += 1


@njit
def _ecu_request(Z, M, F, RX, SEC, buf, crypto, ff, ff_first):
    """``EcuNode.on_frame`` for DRIVER_REQUEST: True when it releases the held command."""
    m = M[M_REQ]
    ctx, msg, tag16, length = crypto
    if ks.forged(m, SEC[S_REQ_RX], buf, m.dlc, ctx, msg, tag16, length):
        _note(Z, ff, ff_first, M_REQ, FAULT_AUTH)
        return False
    ok = kf.receive(F, m, RX[R_REQ], buf, m.dlc, Z.ek)
    Z.awaiting = max(0, Z.awaiting - 1)
    if ok:
        w = kf.load(buf, m.dlc)
        Z.req_kind = kf.get(w, F[U_KIND])
        Z.req_mode = kf.get(w, F[U_MODE])
        Z.req_id = kf.get(w, F[U_ID])
    else:
        _note(Z, ff, ff_first, M_REQ, RX[R_REQ].faults)
    if Z.held and Z.awaiting == 0:
        Z.held = 0
        return True
    return False


@njit
def _app_recommend(Z, M, F, buf, reqlog, scratch_rx) -> None:
    """``AppNode.on_frame`` for MODE_RECOMMEND: decoded (a one-off decode: DLC, CHECKSUM,
    ranges), decided; the answer is built by the caller."""
    m = M[M_REC]
    rx = scratch_rx[0]
    rx.last_counter = -1
    rx.last_rx_tick = -1
    if kf.receive(F, m, rx, buf, m.dlc, 0):
        w = kf.load(buf, m.dlc)
        _app_decide(Z, kf.get(w, F[U_REC]), kf.get(w, F[U_REC_ACTIVE]),
                    kf.get(w, F[U_REC_REASON]), reqlog)


@njit
def run(Za, M, F, FAULT_BITS, RX, SEC, crypto, phis, flows, x, pp, v, acc, zf, speed_mps,
        true_grade, segment, noise, sup_noise, std, rmin, lsb, full, P, T, S, I, O,
        obs, rows, hashbuf, ff, ff_first, reqlog, log_id, log_dlc, log_data, k_end):
    """Run the lockstep ticks from ``Z.k`` up to ``k_end`` (or the route's end). Returns
    ``OK`` or ``LOCKSTEP_BROKEN`` (a tick whose command did not come: ``Z.k`` is that tick)."""
    Z = Za[0]
    ctx, msg, tag16, length = crypto
    buf = np.zeros(8, np.uint8)        # the frame on the bus (processed before the next)
    held = np.zeros(8, np.uint8)       # the ECU's command, held for the driver's answer
    scratch_rx = RX[R_CMD:R_CMD + 1].copy()     # (the app's one-off decodes)
    sensed = np.zeros(5)
    zeta = np.zeros(kp.N_AUG)           # the plant step's scratch
    flow_q = np.zeros(flows.shape[2])
    counts = np.zeros(5, np.int64)
    end = min(k_end, Z.n)
    while Z.k < end:
        k = Z.k
        # ---- the plant's frames (PlantNode.emit)
        if k >= Z.noise_k:
            for c in range(5):
                Z.gain[c] = Z.noise_gain
        ba, wa, sws, cur = kp.sensed(x, Z.zf, pp, Z.has_actuator != 0)
        sensed[0], sensed[1], sensed[2], sensed[3], sensed[4] = ba, wa, sws, cur, speed_mps[k]
        quantise_into(sensed, noise[k - Z.noise_base], std, Z.gain, rmin, lsb, full, counts)
        if k % Z.p_speed == 0:
            m = M[M_SPEED]
            kf.seal(m, buf, kf.put(0, F[U_SPEED], counts[4]), Z.ctr[M_SPEED], True)
            Z.ctr[M_SPEED] = (Z.ctr[M_SPEED] + 1) & 0xF
            Z.sent[M_SPEED] += 1
            _log(Z, M_SPEED, m, buf, log_id, log_dlc, log_data)
            if kf.receive(F, m, RX[R_SPEED], buf, m.dlc, Z.ek):
                Z.speed_raw = kf.get(kf.load(buf, m.dlc), F[U_SPEED])
            else:
                _note(Z, ff, ff_first, M_SPEED, RX[R_SPEED].faults)
        if k % Z.p_supply == 0:
            m = M[M_SUPPLY]
            volts = v[0] + Z.sup_std * sup_noise[Z.supply_next]
            Z.supply_next += 1
            raw = (volts - Z.sup_min) / Z.sup_lsb
            if np.isnan(volts):
                c = 0
            elif raw <= 0.0:
                c = 0
            elif raw >= Z.sup_full:
                c = Z.sup_full
            else:
                c = kf.round_half_away(raw)
            kf.seal(m, buf, kf.put(0, F[U_SUPPLY], c), Z.ctr[M_SUPPLY], True)
            Z.ctr[M_SUPPLY] = (Z.ctr[M_SUPPLY] + 1) & 0xF
            Z.sent[M_SUPPLY] += 1
            _log(Z, M_SUPPLY, m, buf, log_id, log_dlc, log_data)
            if kf.receive(F, m, RX[R_SUPPLY], buf, m.dlc, Z.ek):
                Z.supply_new = kf.get(kf.load(buf, m.dlc), F[U_SUPPLY])
            else:
                _note(Z, ff, ff_first, M_SUPPLY, RX[R_SUPPLY].faults)
        if k % Z.p_truth == 0:          # (nobody receives it: built for the log)
            m = M[M_TRUTH]
            if Z.log_on:
                w = kf.put(0, F[U_TRUE_ROAD], kf.to_raw(F[U_TRUE_ROAD], zf[k]))
                w = kf.put(w, F[U_TRUE_DTD], kf.to_raw(F[U_TRUE_DTD], x[3] - Z.zf))
                w = kf.put(w, F[U_TRUE_SWS], kf.to_raw(F[U_TRUE_SWS], x[2] - x[3]))
                w = kf.put(w, F[U_TRUE_GRADE], kf.to_raw(F[U_TRUE_GRADE], float(true_grade[k])))
                w = kf.put(w, F[U_SEGMENT], kf.to_raw(F[U_SEGMENT], float(segment[k])))
                kf.seal(m, buf, w, Z.ctr[M_TRUTH], True)
            Z.ctr[M_TRUTH] = (Z.ctr[M_TRUTH] + 1) & 0xF          # (no COUNTER signal: Tx counts)
            Z.sent[M_TRUTH] += 1
            _log(Z, M_TRUTH, m, buf, log_id, log_dlc, log_data)
        if k % Z.p_energy == 0:         # (the app shows it: built for the log)
            m = M[M_ENERGY]
            if Z.log_on:
                w = kf.put(0, F[U_STORED], kf.to_raw(F[U_STORED], acc[kp.A_STORED]))
                w = kf.put(w, F[U_DRAWN], kf.to_raw(F[U_DRAWN], acc[kp.A_SUPPLY]))
                kf.seal(m, buf, w, Z.ctr[M_ENERGY], True)
            Z.ctr[M_ENERGY] = (Z.ctr[M_ENERGY] + 1) & 0xF          # (no COUNTER signal: Tx counts)
            Z.sent[M_ENERGY] += 1
            _log(Z, M_ENERGY, m, buf, log_id, log_dlc, log_data)
        m = M[M_SENSORS]
        w = kf.put(0, F[U_SENS], counts[0])
        w = kf.put(w, F[U_SENS + 1], counts[1])
        w = kf.put(w, F[U_SENS + 2], counts[2])
        w = kf.put(w, F[U_SENS + 3], counts[3])
        kf.seal(m, buf, w, Z.ctr[M_SENSORS], True)
        Z.ctr[M_SENSORS] = (Z.ctr[M_SENSORS] + 1) & 0xF
        Z.sent[M_SENSORS] += 1
        _log(Z, M_SENSORS, m, buf, log_id, log_dlc, log_data)
        # ---- the ECU receives it (EcuNode.on_frame)
        if kf.receive(F, m, RX[R_SENSORS], buf, m.dlc, Z.ek):
            w = kf.load(buf, m.dlc)
            for c in range(4):
                Z.counts[c] = kf.get(w, F[U_SENS + c])
            Z.seq = kf.counter_of(m, buf) & 0x3
        else:
            for c in range(4):
                Z.counts[c] = -1
            Z.seq = kf.counter_of(m, buf) & 0x3
            _note(Z, ff, ff_first, M_SENSORS, RX[R_SENSORS].faults)
        # ---- the ECU's tick (EcuNode.tick)
        ek = Z.ek
        speed = Z.speed_raw
        if kf.timed_out(RX[R_SPEED], ek):
            Z.link_faults |= kf.FAULT_TIMEOUT
            speed = -1
        elif RX[R_SPEED].valid == 0:
            speed = -1
        supply = Z.supply_new
        Z.supply_new = -1
        if kf.timed_out(RX[R_SUPPLY], ek):
            Z.link_faults |= kf.FAULT_TIMEOUT
        link = Z.link_faults
        inp = I[0]
        inp.tick = ek
        for c in range(4):
            inp.counts[c] = Z.counts[c]
        inp.counts[4] = speed
        inp.supply = supply
        inp.req_kind, inp.req_mode, inp.req_counter = Z.req_kind, Z.req_mode, Z.req_id
        inp.link_faults = link
        ecu.tick(P, T, S, I, O)
        o = O[0]
        Z.ek = ek + 1
        Z.link_faults = 0
        m = M[M_CMD]
        w = kf.put(0, F[U_DUTY], o.duty_q15)
        w = kf.put(w, F[U_REGEN], o.regen)
        w = kf.put(w, F[U_ENABLE], o.enable)
        w = kf.put(w, F[U_SEQ], Z.seq)
        kf.seal(m, held, w, Z.ctr[M_CMD], False)
        Z.ctr[M_CMD] = (Z.ctr[M_CMD] + 1) & 0xF
        Z.sent[M_CMD] += 1
        ks.protect(m, SEC[S_CMD_TX], held, ctx, msg, tag16, length)
        grade = UNKNOWN_GRADE_ON_BUS if o.grade == fp.GRADE_UNKNOWN else o.grade
        Z.status_faults |= o.faults
        if ek % Z.p_status == 0:
            m = M[M_STATUS]
            w = kf.put(0, F[U_ST_ACTIVE], o.active_mode)
            w = kf.put(w, F[U_ST_GRADE], grade)
            w = kf.put(w, F[U_ST_REASON], o.reason)
            for j in range(FAULT_BITS.shape[0]):
                w = kf.put(w, F[U_FAULTS + j], 1 if Z.status_faults & FAULT_BITS[j] else 0)
            w = kf.put(w, F[U_ST_BA], o.ba_rms_mmps2)
            w = kf.put(w, F[U_ST_DTD], (o.dtd_rms_um + 5) // 10)
            kf.seal(m, buf, w, Z.ctr[M_STATUS], True)
            Z.ctr[M_STATUS] = (Z.ctr[M_STATUS] + 1) & 0xF
            Z.sent[M_STATUS] += 1
            Z.status_faults = 0
            _log(Z, M_STATUS, m, buf, log_id, log_dlc, log_data)
            Z.n_status += 1                                 # (the app's clock)
            Z.t = (Z.n_status - 1) * Z.app_p_status
            m = M[M_EST]
            if Z.log_on:
                r = o.road_est_um
                r10 = (abs(r) + 5) // 10                # (half away from zero)
                w = kf.put(0, F[U_ROAD_EST], r10 if r >= 0 else -r10)
                w = kf.put(w, F[U_DTD_EST], o.dtd_est_um)
                w = kf.put(w, F[U_GQ], o.gq_est_log_c)
                w = kf.put(w, F[U_FORCE], o.force_cmd_n)
                kf.seal(m, buf, w, Z.ctr[M_EST], True)
            Z.ctr[M_EST] = (Z.ctr[M_EST] + 1) & 0xF          # (no COUNTER signal: Tx counts)
            Z.sent[M_EST] += 1
            _log(Z, M_EST, m, buf, log_id, log_dlc, log_data)
        lr = Z.last_rec
        if (ek % Z.p_rec == 0 or lr[0] != o.recommended_mode or lr[1] != o.active_mode
                or lr[2] != o.reason or lr[3] != o.override):
            lr[0], lr[1], lr[2], lr[3] = o.recommended_mode, o.active_mode, o.reason, o.override
            Z.awaiting += 1
            Z.held = 1                                      # (lockstep: until answered)
            m = M[M_REC]
            w = kf.put(0, F[U_REC], o.recommended_mode)
            w = kf.put(w, F[U_REC_GRADE], grade)
            w = kf.put(w, F[U_REC_ACTIVE], o.active_mode)
            w = kf.put(w, F[U_REC_REASON], o.reason)
            w = kf.put(w, F[U_REC_OVERRIDE], o.override)
            kf.seal(m, buf, w, Z.ctr[M_REC], True)
            Z.ctr[M_REC] = (Z.ctr[M_REC] + 1) & 0xF
            Z.sent[M_REC] += 1
            _log(Z, M_REC, m, buf, log_id, log_dlc, log_data)
            _app_recommend(Z, M, F, buf, reqlog, scratch_rx)
            m = M[M_REQ]                                    # the app's answer
            w = kf.put(0, F[U_KIND], Z.kind)
            w = kf.put(w, F[U_MODE], Z.rmode)
            w = kf.put(w, F[U_ID], Z.rid)
            kf.seal(m, buf, w, Z.ctr[M_REQ], True)
            Z.ctr[M_REQ] = (Z.ctr[M_REQ] + 1) & 0xF
            Z.sent[M_REQ] += 1
            ks.protect(m, SEC[S_REQ_TX], buf, ctx, msg, tag16, length)
            _log(Z, M_REQ, m, buf, log_id, log_dlc, log_data)
            release = _ecu_request(Z, M, F, RX, SEC, buf, crypto, ff, ff_first)
        else:                   # (an answer still owed holds the command: lockstep broken)
            Z.held = 1 if Z.awaiting else 0
            release = Z.held == 0
        _record(Z, o, inp, speed, supply, link, rows, hashbuf)
        if release:
            m = M[M_CMD]
            _log(Z, M_CMD, m, held, log_id, log_dlc, log_data)
            _plant_cmd(Z, M, F, RX, SEC, held, crypto)
        # ---- the plant steps (PlantNode.step)
        if Z.cmd_fresh == 0:
            return LOCKSTEP_BROKEN
        duty, regen, enable = Z.cmd_duty, Z.cmd_regen != 0, Z.cmd_enable != 0
        fallback = Z.cmd_tick < 0 or k - Z.cmd_tick > Z.cmd_timeout
        if fallback:
            duty, regen, enable = 0, False, False
            Z.fallback_ticks += 1
        d = min(1.0, max(-1.0, duty / 32768.0))
        limited, contact, lifted = kp.advance_into(
            phis, flows, x, Z.zf, zf[k + 1], d, regen, enable and Z.has_actuator != 0, Z.dt,
            pp, v, Z.ind_l, Z.track != 0, acc, zeta, flow_q)
        if contact and not Z.in_bump:
            Z.bump_contacts += 1
        if lifted and not Z.lifted:
            Z.lift_offs += 1
        Z.in_bump, Z.lifted = int(contact), int(lifted)
        Z.limited_steps += int(limited)
        Z.zf = zf[k + 1]
        kp.observe_into(x, Z.zf, pp, Z.has_actuator != 0, acc, obs, k)
        obs[k, N_OBS] = duty / 32768.0 if enable else 0.0
        obs[k, N_OBS + 1] = 1.0 if fallback else 0.0
        obs[k, N_OBS + 2] = Z.auth_failures - Z.auth_booked
        Z.auth_booked = Z.auth_failures
        Z.k = k + 1
        Z.cmd_fresh = 0
    return OK
