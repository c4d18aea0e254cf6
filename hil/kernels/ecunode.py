"""The ECU node's frame handling compiled: what ``hil.nodes.EcuNode`` does with a received
frame (``receive``: the receive table, one branch per message the firmware listens to,
``firmware.safety.RX_CHECKS`` on the DBC's layout) and per tick (``tick``: the timeouts, the
inputs, the compiled ECU tick ``firmware.ecu.tick``, the frames it sends, signed where
SecOC secures them), and the tick's record (``record``: the hashed row, the trace row).

The same functions serve the ECU node of ``hil run`` (one call per frame and per tick) and
the compiled SIL loop (``hil.kernels.silloop``): one source for both harnesses.

``ECU_NODE``: the node's state (its receive-side values, the driver's latest request, the
answers it waits for, the link faults of the tick, the OR of the fault words since the last
ECU_STATUS, the last recommendation sent, the transmit COUNTERs and frames sent per message);
``ff``/``ff_first``: the frame faults per message and fault bit, with a stamp of when each
was first seen (the report's order).
"""

from __future__ import annotations

import numpy as np

from firmware import adc
from firmware import params as fp
from firmware.kernels import njit
from firmware.safety import FAULT_AUTH, FAULT_TIMEOUT
from firmware import ecu
from hil.kernels import frames as kf
from hil.kernels import secoc as ks
from hil.kernels.bus import (M_CMD, M_EST, M_REC, M_SENSORS, M_SPEED, M_STATUS,
                             M_SUPPLY, NMSG, R_REQ, R_SENSORS, R_SPEED, R_SUPPLY, S_CMD_TX,
                             S_REQ_RX, U_DTD_EST, U_DUTY, U_ENABLE, U_FAULTS, U_FORCE, U_GQ,
                             U_ID, U_KIND, U_MODE, U_REC, U_REC_ACTIVE, U_REC_GRADE,
                             U_REC_OVERRIDE, U_REC_REASON, U_REGEN, U_ROAD_EST, U_SENS, U_SEQ,
                             U_SPEED, U_ST_ACTIVE, U_ST_BA, U_ST_DTD, U_ST_GRADE, U_ST_REASON, U_ST_DEGRADED,
                             U_SUPPLY)

ECU_NODE = np.dtype([
    ("k", "i8"), ("speed_raw", "i8"), ("supply_new", "i8"), ("req_kind", "i8"),
    ("req_mode", "i8"), ("req_id", "i8"), ("awaiting", "i8"), ("link_faults", "i8"),
    ("seq", "i8"), ("status_faults", "i8"), ("last_rec", "i8", (4,)), ("p_status", "i8"),
    ("p_rec", "i8"), ("counts", "i8", (4,)), ("ff_stamp", "i8"),
    ("speed", "i8"), ("supply", "i8"), ("link", "i8"),        # the last tick's, for record
    ("lockstep", "i8"), ("secured", "i8"),
    ("ctr", "i8", (NMSG,)), ("sent", "i8", (NMSG,))])
ROW_BYTES = 93           # a hashed row (hil.nodes.HASHED, little-endian, no padding)
UNKNOWN_GRADE_ON_BUS = 7
# receive's answers
RX_NONE, RX_SAMPLE, RX_NO_SAMPLE, RX_RELEASE = 0, 1, 2, 3


@njit
def note(E, ff, ff_first, mi, faults) -> None:
    """``EcuNode._note``: the link faults of the tick, counted per message and fault bit."""
    E.link_faults |= faults
    for b in range(32):
        if faults & (1 << b):
            if ff[mi, b] == 0:
                ff_first[mi, b] = E.ff_stamp
                E.ff_stamp += 1
            ff[mi, b] += 1


@njit
def _value(E, F, m, rx, ff, ff_first, mi, u, buf, n):
    """A one-signal message (VEHICLE_SPEED, PLANT_SUPPLY: unsigned counts): its raw value
    if the frame is usable, else -1 (the node's "none") with its faults noted."""
    if kf.receive(F, m, rx, buf, n, E.k):
        return kf.get(kf.load(buf, m.dlc), F[u])
    note(E, ff, ff_first, mi, rx.faults)
    return -1


@njit
def receive(Ea, M, F, RX, SEC, crypto, ff, ff_first, mi, buf, n):
    """A frame of a message the ECU listens to (``mi``: VEHICLE_SPEED, PLANT_SUPPLY,
    PLANT_SENSORS, DRIVER_REQUEST; ``buf``: its ``n`` bytes, zero beyond them), checked and
    decoded as ``EcuNode.on_frame`` does. Returns ``RX_SAMPLE`` (a valid sensor sample, in
    ``E.counts``) or ``RX_NO_SAMPLE`` (an invalid one) for PLANT_SENSORS, ``RX_RELEASE``
    when after a driver request no answer is awaited (a held command goes), else
    ``RX_NONE``. (``Ea``: the node's one-element record array.)"""
    E = Ea[0]
    m = M[mi]
    if mi == M_SENSORS:
        if kf.receive(F, m, RX[R_SENSORS], buf, n, E.k):
            w = kf.load(buf, m.dlc)
            for c in range(4):
                E.counts[c] = kf.get(w, F[U_SENS + c])
            E.seq = kf.counter_of(m, buf) & 0x3
            return RX_SAMPLE
        if n > m.counter_bit // 8:
            E.seq = kf.counter_of(m, buf) & 0x3              # (as sent)
        note(E, ff, ff_first, mi, RX[R_SENSORS].faults)
        return RX_NO_SAMPLE
    if mi == M_SPEED:
        v = _value(E, F, m, RX[R_SPEED], ff, ff_first, mi, U_SPEED, buf, n)
        if v >= 0:
            E.speed_raw = v
        return RX_NONE
    if mi == M_SUPPLY:
        v = _value(E, F, m, RX[R_SUPPLY], ff, ff_first, mi, U_SUPPLY, buf, n)
        if v >= 0:
            E.supply_new = v
        return RX_NONE
    # DRIVER_REQUEST: forged or replayed frames are not the app's answer (state untouched)
    ctx, msg, tag16, length = crypto
    if E.secured and ks.forged(m, SEC[S_REQ_RX], buf, n, ctx, msg, tag16, length):
        note(E, ff, ff_first, mi, FAULT_AUTH)
        return RX_NONE
    ok = kf.receive(F, m, RX[R_REQ], buf, n, E.k)
    E.awaiting = max(0, E.awaiting - 1)
    if ok:
        w = kf.load(buf, m.dlc)
        E.req_kind = kf.get(w, F[U_KIND])
        E.req_mode = kf.get(w, F[U_MODE])
        E.req_id = kf.get(w, F[U_ID])
    else:
        note(E, ff, ff_first, mi, RX[R_REQ].faults)
    return RX_RELEASE if E.awaiting == 0 else RX_NONE


@njit
def _frame(E, M, mi, buf, w, with_checksum) -> None:
    """A frame of the ECU's: COUNTER (and CHECKSUM) sealed, counted as sent."""
    kf.seal(M[mi], buf, w, E.ctr[mi], with_checksum)
    E.ctr[mi] = (E.ctr[mi] + 1) & 0xF
    E.sent[mi] += 1


@njit
def tick(Ea, M, F, FAULT_BITS, RX, SEC, crypto, P, T, S, I, O, sample, c0, c1, c2, c3,
         out_mi, out):
    """``EcuNode.tick`` from its pending sample (``sample``: the counts ``c0..c3``; else
    none) to the frames it sends, in ``out_mi``/``out`` (message index, payload): the
    signed ACTUATOR_CMD first, then ECU_STATUS and ECU_ESTIMATES (every ``p_status``
    ticks) and MODE_RECOMMEND (every ``p_rec`` ticks and on change: one more answer awaited;
    none in realtime, where nobody waits). Where the command goes (held,
    last, first) is the caller's. Returns (the number of frames, answers awaited)."""
    E = Ea[0]
    k = E.k
    speed = E.speed_raw
    if kf.timed_out(RX[R_SPEED], k):
        E.link_faults |= FAULT_TIMEOUT
        speed = -1
    elif RX[R_SPEED].valid == 0:
        speed = -1
    supply = E.supply_new
    E.supply_new = -1
    if kf.timed_out(RX[R_SUPPLY], k):
        E.link_faults |= FAULT_TIMEOUT
    link = E.link_faults
    inp = I[0]
    inp.tick = k
    if sample:
        inp.counts[0], inp.counts[1], inp.counts[2], inp.counts[3] = c0, c1, c2, c3
    else:
        inp.counts[0] = inp.counts[1] = inp.counts[2] = inp.counts[3] = adc.NO_SAMPLE
    inp.counts[4] = speed
    inp.supply = supply
    inp.req_kind, inp.req_mode, inp.req_counter = E.req_kind, E.req_mode, E.req_id
    inp.link_faults = link
    ecu.tick(P, T, S, I, O)
    o = O[0]
    E.k = k + 1
    E.link_faults = 0
    E.speed, E.supply, E.link = speed, supply, link
    w = kf.put(0, F[U_DUTY], o.duty_q15)
    w = kf.put(w, F[U_REGEN], o.regen)
    w = kf.put(w, F[U_ENABLE], o.enable)
    w = kf.put(w, F[U_SEQ], E.seq)
    _frame(E, M, M_CMD, out[0], w, E.secured == 0)     # (with SecOC: CHECKSUM after the MAC)
    if E.secured:
        ctx, msg, tag16, length = crypto
        ks.protect(M[M_CMD], SEC[S_CMD_TX], out[0], ctx, msg, tag16, length)
    out_mi[0] = M_CMD
    nf = 1
    grade = UNKNOWN_GRADE_ON_BUS if o.grade == fp.GRADE_UNKNOWN else o.grade
    E.status_faults |= o.faults
    if k % E.p_status == 0:
        w = kf.put(0, F[U_ST_ACTIVE], o.active_mode)
        w = kf.put(w, F[U_ST_GRADE], grade)
        w = kf.put(w, F[U_ST_REASON], o.reason)
        for j in range(FAULT_BITS.shape[0]):
            w = kf.put(w, F[U_FAULTS + j], 1 if E.status_faults & FAULT_BITS[j] else 0)
        w = kf.put(w, F[U_ST_BA], o.ba_rms_mmps2)
        w = kf.put(w, F[U_ST_DTD], (o.dtd_rms_um + 5) // 10)
        w = kf.put(w, F[U_ST_DEGRADED], o.degraded)
        _frame(E, M, M_STATUS, out[nf], w, True)
        out_mi[nf] = M_STATUS
        E.status_faults = 0
        r = o.road_est_um
        r10 = (abs(r) + 5) // 10                            # (half away from zero)
        w = kf.put(0, F[U_ROAD_EST], r10 if r >= 0 else -r10)
        w = kf.put(w, F[U_DTD_EST], o.dtd_est_um)
        w = kf.put(w, F[U_GQ], o.gq_est_log_c)
        w = kf.put(w, F[U_FORCE], o.force_cmd_n)
        _frame(E, M, M_EST, out[nf + 1], w, True)
        out_mi[nf + 1] = M_EST
        nf += 2
    lr = E.last_rec
    if (k % E.p_rec == 0 or lr[0] != o.recommended_mode or lr[1] != o.active_mode
            or lr[2] != o.reason or lr[3] != o.override):
        lr[0], lr[1], lr[2], lr[3] = o.recommended_mode, o.active_mode, o.reason, o.override
        E.awaiting += 1
        w = kf.put(0, F[U_REC], o.recommended_mode)
        w = kf.put(w, F[U_REC_GRADE], grade)
        w = kf.put(w, F[U_REC_ACTIVE], o.active_mode)
        w = kf.put(w, F[U_REC_REASON], o.reason)
        w = kf.put(w, F[U_REC_OVERRIDE], o.override)
        _frame(E, M, M_REC, out[nf], w, True)
        out_mi[nf] = M_REC
        nf += 1
    if E.lockstep == 0:
        E.awaiting = 0
    return nf, E.awaiting


@njit
def _wr(buf, pos, v, nbytes):
    for i in range(nbytes):
        buf[pos + i] = (v >> (8 * i)) & 0xFF
    return pos + nbytes


@njit
def record(Ea, I, O, hashbuf, pos, row) -> int:
    """``EcuNode.record``: the last tick's hashed row (``hil.nodes.HASHED``) into
    ``hashbuf`` at ``pos``, its trace row (``hil.nodes.ECU_TRACE``) into ``row``. Returns
    the position after the row."""
    E = Ea[0]
    inp, o = I[0], O[0]
    p = _wr(hashbuf, pos, inp.tick, 8)
    for c in range(4):
        p = _wr(hashbuf, p, inp.counts[c], 4)
    p = _wr(hashbuf, p, E.speed, 4)
    p = _wr(hashbuf, p, E.supply, 4)
    p = _wr(hashbuf, p, inp.req_kind, 4)
    p = _wr(hashbuf, p, inp.req_mode, 4)
    p = _wr(hashbuf, p, inp.req_counter, 4)
    p = _wr(hashbuf, p, E.link, 4)
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
    p = _wr(hashbuf, p, o.degraded, 1)
    p = _wr(hashbuf, p, o.force_cmd_n, 4)
    p = _wr(hashbuf, p, o.road_est_um, 4)
    p = _wr(hashbuf, p, o.dtd_est_um, 4)
    p = _wr(hashbuf, p, o.gq_est_log_c, 4)
    p = _wr(hashbuf, p, o.ba_rms_mmps2, 4)
    p = _wr(hashbuf, p, o.dtd_rms_um, 4)
    p = _wr(hashbuf, p, 0, 4)                                 # (reserved)
    row[0], row[1], row[2], row[3], row[4] = (o.road_est_um, o.dtd_est_um, o.force_cmd_n,
                                              o.grade, o.active_mode)
    row[5], row[6], row[7], row[8] = o.recommended_mode, o.faults, o.enable, o.reason
    row[9] = o.degraded
    return p
