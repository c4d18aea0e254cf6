"""The SIL's lockstep loop compiled (issue 37): the plant, ECU and driver-app nodes of
``hil.nodes`` and the bus between them as one numba function that runs tick after tick until
the next event of Python's calendar (``hil.nodes.fastsil``: a block of sensor noise, progress, a
fault campaign's window), the same frames in the same order as ``hil.nodes.run_in_process``
and the same bytes (``tests/test_silloop.py`` holds the two together; ``run_in_process``
stays the path of the runs this loop does not cover: ``hil.nodes.fastsil.eligible``).

Per tick k, as ``hil.nodes``' docstring tells the protocol: the plant samples its sensors and
sends VEHICLE_SPEED, PLANT_SUPPLY, SIM_TRUTH (every 10 ms), ENERGY_STATUS (100 ms) and
PLANT_SENSORS; the ECU ticks and sends ECU_STATUS and ECU_ESTIMATES (10 ms) and
MODE_RECOMMEND (100 ms and on change), the app answers that with a DRIVER_REQUEST, then the
ECU's signed ACTUATOR_CMD goes to the plant, which steps. The ECU's side is the ECU node's
own compiled code (``hil.kernels.ecunode``: ``receive`` per frame, ``tick``, ``record``), the
same calls ``hil.nodes.EcuNode`` makes in ``hil run``.

State: the record ``Z`` (``SIL``: the plant's and the app's scalars, their transmit COUNTERs,
the frames sent and seen per message) and the ECU node's record; the tables of
``hil.kernels.bus``; the plant's arrays (``hil.sim.plant.QuarterCarPlant``'s); the ECU's records
(``firmware``); the per-tick outputs (the plant's observations, the ECU's trace rows,
the hashed rows, the frame log, the driver's requests, what the driver was told).
"""

from __future__ import annotations

import numpy as np

from firmware import params as fp
from firmware.kernels import njit
from firmware.modes import REASON_NONE
from hil.kernels import ecunode as ken
from hil.kernels import frames as kf
from hil.kernels import plant as kp
from hil.kernels import secoc as ks
from hil.kernels.bus import (M_CMD, M_ENERGY, M_REC, M_REQ, M_SENSORS, M_SPEED,
                             M_STATUS, M_SUPPLY, M_TRUTH, NMSG, S_CMD_RX, S_REQ_TX, U_DRAWN,
                             U_DUTY, U_ENABLE, U_ID, U_KIND, U_MODE, U_REC, U_REC_ACTIVE,
                             U_FAULTS, U_REC_REASON, U_REGEN, U_SEGMENT, U_SENS, U_SEQ,
                             U_SPEED, U_ST_REASON, U_STORED, U_SUPPLY, U_TRUE_DTD,
                             U_TRUE_GRADE, U_TRUE_ROAD, U_TRUE_SWS)
from hil.kernels.sensors import quantise_faulted, quantise_into, to_counts

# the driver policies here: a script's decisions are Python's (the calendar's spans)
POLICIES = ("auto", "fixed", "refuse", "script")
P_SCRIPT = 3
ROW_BYTES = ken.ROW_BYTES
FRAMES_PER_TICK = 12     # at most, for the frame log's size
OK, LOCKSTEP_BROKEN = 0, 1
N_OBS = len(kp.OBS)      # the plant's observations, then the duty applied, fallback, rejected

SIL = np.dtype([
    # the plant node
    ("k", "i8"), ("n", "i8"), ("dt", "f8"), ("p_speed", "i8"), ("p_supply", "i8"),
    ("p_truth", "i8"), ("p_energy", "i8"), ("cmd_timeout", "i8"), ("cmd_duty", "i8"),
    ("cmd_regen", "i8"), ("cmd_enable", "i8"), ("cmd_tick", "i8"), ("cmd_fresh", "i8"),
    ("cmd_seq", "i8"), ("bad_cmd", "i8"), ("stale_cmd", "i8"),
    ("fallback_ticks", "i8"), ("auth_failures", "i8"), ("auth_booked", "i8"),
    ("has_actuator", "i8"), ("track", "i8"), ("ind_l", "f8"), ("zf", "f8"),
    ("in_bump", "i8"), ("lifted", "i8"), ("bump_contacts", "i8"), ("lift_offs", "i8"),
    ("limited_steps", "i8"), ("noise_k", "i8"), ("noise_gain", "f8"), ("gain", "f8", (5,)),
    ("noise_base", "i8"), ("supply_next", "i8"), ("sup_std", "f8"), ("sup_min", "f8"),
    ("sup_lsb", "f8"), ("sup_full", "i8"),
    # the driver app
    ("policy", "i8"), ("app_mode", "i8"), ("reaction", "i8"), ("n_status", "i8"),
    ("t", "i8"), ("kind", "i8"), ("rmode", "i8"), ("rid", "i8"), ("shown", "i8"),
    ("shown_since", "i8"), ("answered", "i8"), ("chosen", "i8"), ("app_p_status", "i8"),
    ("fs_word", "i8"), ("fs_reason", "i8"),      # what the driver was last told (faults_seen)
    # a fault campaign's plant: its receiver of every command on the wire runs too
    ("wire", "i8"),
    # the C parity record: the ECU state's bytes of the fixed-point hand-over, per tick
    ("fx_on", "i8"), ("fx_off", "i8"),
    # the bus: the plant's and app's COUNTERs and frames sent, frames seen, per message;
    # the buffers' fill
    ("ctr", "i8", (NMSG,)), ("sent", "i8", (NMSG,)), ("seen", "i8", (NMSG,)),
    ("log_on", "i8"), ("nlog", "i8"), ("hpos", "i8"), ("nreq", "i8"), ("nfs", "i8")])
S_CMD_WIRE = 4           # the SIL's SecOC table: hil.kernels.bus' rows, then the wire's verifier
R_WIRE = 1               # the plant's receivers: ACTUATOR_CMD's, then the wire's


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
    """``AppNode._decide`` for the policies ``auto``, ``fixed`` and ``refuse`` (``script``:
    no entry of the script is due outside Python's spans)."""
    t = Z.t
    if Z.policy == P_SCRIPT:
        return
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
def _plant_cmd(Z, M, F, PRX, SEC, buf, crypto) -> None:
    """``PlantNode._receive_cmd`` outside a fault's window: SecOC first, then the frame
    checks; a valid command is applied, and ends the tick if it answers this tick's sensor
    frame. In a fault campaign (``Z.wire``) the receiver of every command on the wire judges
    it first (``cmd_rx_wire``, ``cmd_auth_wire``: the windows that lose commands read it)."""
    m = M[M_CMD]
    ctx, msg, tag16, length = crypto
    if Z.wire != 0 and not ks.forged(m, SEC[S_CMD_WIRE], buf, m.dlc, ctx, msg, tag16, length):
        kf.receive(F, m, PRX[R_WIRE], buf, m.dlc, Z.k)
    if ks.forged(m, SEC[S_CMD_RX], buf, m.dlc, ctx, msg, tag16, length):
        Z.auth_failures += 1
        return
    if not kf.receive(F, m, PRX[0], buf, m.dlc, Z.k):
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
def _app_decode(m, F, buf, scratch_rx) -> bool:
    """The app's decode of a frame (``Codec.decode``: a one-off check of DLC, CHECKSUM and
    ranges, no COUNTER state)."""
    rx = scratch_rx[0]
    rx.last_counter = -1
    rx.last_rx_tick = -1
    return kf.receive(F, m, rx, buf, m.dlc, 0)


@njit
def _app_recommend(Z, M, F, buf, reqlog, scratch_rx) -> None:
    """``AppNode.on_frame`` for MODE_RECOMMEND: decoded, decided; the answer is built by the
    caller."""
    m = M[M_REC]
    if _app_decode(m, F, buf, scratch_rx):
        w = kf.load(buf, m.dlc)
        _app_decide(Z, kf.get(w, F[U_REC]), kf.get(w, F[U_REC_ACTIVE]),
                    kf.get(w, F[U_REC_REASON]), reqlog)


@njit
def _app_status(Z, M, F, FAULT_BITS, buf, fslog, scratch_rx) -> None:
    """``AppNode.on_frame`` for ECU_STATUS: the app's clock, and what the driver is told
    (``faults_seen``: the tick, fault word and REASON at each change)."""
    Z.n_status += 1
    Z.t = (Z.n_status - 1) * Z.app_p_status
    m = M[M_STATUS]
    if _app_decode(m, F, buf, scratch_rx):
        w = kf.load(buf, m.dlc)
        word = 0
        for j in range(len(FAULT_BITS)):
            if kf.get(w, F[U_FAULTS + j]) != 0:
                word |= FAULT_BITS[j]
        reason = kf.get(w, F[U_ST_REASON])
        if word != Z.fs_word or reason != Z.fs_reason:
            Z.fs_word = word
            Z.fs_reason = reason
            j = Z.nfs
            fslog[j, 0], fslog[j, 1], fslog[j, 2] = Z.t, word, reason
            Z.nfs = j + 1


@njit
def _send(Z, mi) -> None:
    """A frame of the plant's or the app's sent: its COUNTER on (``Tx`` keeps one for every
    message), counted."""
    Z.ctr[mi] = (Z.ctr[mi] + 1) & 0xF
    Z.sent[mi] += 1


@njit
def run(Za, Ea, M, F, FAULT_BITS, ERX, PRX, ESEC, SEC, crypto, phis, flows, x, pp, v, acc, zf,
        speed_mps, true_grade, segment, noise, sup_noise, std, rmin, lsb, full, SF, P, T, S, I, O,
        obs, rows, hashbuf, ff, ff_first, reqlog, fslog, log_id, log_dlc, log_data, s_bytes,
        fx_rows, k_end):
    """Run the lockstep ticks from ``Z.k`` up to ``k_end`` (or the route's end). ``Ea``, the
    ECU node's state with its receivers ``ERX`` and SecOC rows ``ESEC`` and its frame faults
    ``ff``/``ff_first`` (``hil.kernels.ecunode``); ``SF``, a sensor fault
    (``hil.kernels.sensors.FAULT``; channel -1: none); ``PRX``, the plant's receiver of
    ACTUATOR_CMD; ``SEC``, the plant's and the app's SecOC rows; ``s_bytes``, the ECU
    state ``S`` as bytes, whose fixed-point hand-over goes to ``fx_rows`` per tick
    (``Z.fx_on``, the C parity record). Returns ``OK`` or
    ``LOCKSTEP_BROKEN`` (a tick whose command did not come: ``Z.k`` is that tick)."""
    Z = Za[0]
    E = Ea[0]
    ctx, msg, tag16, length = crypto
    buf = np.zeros(8, np.uint8)        # the frame on the bus (processed before the next)
    out_mi = np.zeros(4, np.int64)     # the ECU's frames of a tick (the command first)
    out = np.zeros((4, 8), np.uint8)
    scratch_rx = PRX[0:1].copy()       # (the app's one-off decodes)
    sensed = np.zeros(5)
    zeta = np.zeros(kp.N_AUG)           # the plant step's scratch
    flow_q = np.zeros(flows.shape[2])
    counts = np.zeros(5, np.int64)
    faulted = SF[0].channel >= 0       # (a sensor fault: the campaign's; else the plain ADC)
    end = min(k_end, Z.n)
    while Z.k < end:
        k = Z.k
        # ---- the plant's frames (PlantNode.emit), each received as it crosses the bus
        if k >= Z.noise_k:
            for c in range(5):
                Z.gain[c] = Z.noise_gain
        ba, wa, sws, cur = kp.sensed(x, Z.zf, pp, Z.has_actuator != 0)
        sensed[0], sensed[1], sensed[2], sensed[3], sensed[4] = ba, wa, sws, cur, speed_mps[k]
        if faulted:
            quantise_faulted(sensed, noise[k - Z.noise_base], std, Z.gain, rmin, lsb, full,
                             counts, SF, k)
        else:
            quantise_into(sensed, noise[k - Z.noise_base], std, Z.gain, rmin, lsb, full, counts)
        if k % Z.p_speed == 0:
            m = M[M_SPEED]
            kf.seal(m, buf, kf.put(0, F[U_SPEED], counts[4]), Z.ctr[M_SPEED], True)
            _send(Z, M_SPEED)
            _log(Z, M_SPEED, m, buf, log_id, log_dlc, log_data)
            ken.receive(Ea, M, F, ERX, ESEC, crypto, ff, ff_first, M_SPEED, buf, m.dlc)
        if k % Z.p_supply == 0:
            m = M[M_SUPPLY]
            c = to_counts(v[0] + Z.sup_std * sup_noise[Z.supply_next], Z.sup_min, Z.sup_lsb,
                          Z.sup_full)
            Z.supply_next += 1
            kf.seal(m, buf, kf.put(0, F[U_SUPPLY], c), Z.ctr[M_SUPPLY], True)
            _send(Z, M_SUPPLY)
            _log(Z, M_SUPPLY, m, buf, log_id, log_dlc, log_data)
            ken.receive(Ea, M, F, ERX, ESEC, crypto, ff, ff_first, M_SUPPLY, buf, m.dlc)
        if k % Z.p_truth == 0:          # (nobody receives it: built for the log)
            m = M[M_TRUTH]
            if Z.log_on:
                w = kf.put(0, F[U_TRUE_ROAD], kf.to_raw(F[U_TRUE_ROAD], zf[k]))
                w = kf.put(w, F[U_TRUE_DTD], kf.to_raw(F[U_TRUE_DTD], x[3] - Z.zf))
                w = kf.put(w, F[U_TRUE_SWS], kf.to_raw(F[U_TRUE_SWS], x[2] - x[3]))
                w = kf.put(w, F[U_TRUE_GRADE], kf.to_raw(F[U_TRUE_GRADE],
                                                         float(true_grade[k])))
                w = kf.put(w, F[U_SEGMENT], kf.to_raw(F[U_SEGMENT], float(segment[k])))
                kf.seal(m, buf, w, Z.ctr[M_TRUTH], True)
            _send(Z, M_TRUTH)
            _log(Z, M_TRUTH, m, buf, log_id, log_dlc, log_data)
        if k % Z.p_energy == 0:         # (the app shows it: built for the log)
            m = M[M_ENERGY]
            if Z.log_on:
                w = kf.put(0, F[U_STORED], kf.to_raw(F[U_STORED], acc[kp.A_STORED]))
                w = kf.put(w, F[U_DRAWN], kf.to_raw(F[U_DRAWN], acc[kp.A_SUPPLY]))
                kf.seal(m, buf, w, Z.ctr[M_ENERGY], True)
            _send(Z, M_ENERGY)
            _log(Z, M_ENERGY, m, buf, log_id, log_dlc, log_data)
        m = M[M_SENSORS]
        w = kf.put(0, F[U_SENS], counts[0])
        w = kf.put(w, F[U_SENS + 1], counts[1])
        w = kf.put(w, F[U_SENS + 2], counts[2])
        w = kf.put(w, F[U_SENS + 3], counts[3])
        kf.seal(m, buf, w, Z.ctr[M_SENSORS], True)
        _send(Z, M_SENSORS)
        _log(Z, M_SENSORS, m, buf, log_id, log_dlc, log_data)
        got = ken.receive(Ea, M, F, ERX, ESEC, crypto, ff, ff_first, M_SENSORS, buf, m.dlc)
        # ---- the ECU's tick (EcuNode.tick): its frames cross the bus in order, the command
        # last (after the driver's answer when a MODE_RECOMMEND went out)
        ek = E.k
        nf, awaiting = ken.tick(Ea, M, F, FAULT_BITS, ERX, ESEC, crypto, P, T, S, I, O,
                                got == ken.RX_SAMPLE, E.counts[0], E.counts[1], E.counts[2],
                                E.counts[3], out_mi, out)
        held = awaiting > 0
        if Z.fx_on != 0:
            for i in range(fx_rows.shape[1]):
                fx_rows[ek, i] = s_bytes[Z.fx_off + i]
        for j in range(1, nf):
            mi = out_mi[j]
            _log(Z, mi, M[mi], out[j], log_id, log_dlc, log_data)
            if mi == M_STATUS:
                _app_status(Z, M, F, FAULT_BITS, out[j], fslog, scratch_rx)
            elif mi == M_REC:
                for i in range(8):
                    buf[i] = out[j, i]
                _app_recommend(Z, M, F, buf, reqlog, scratch_rx)
                m = M[M_REQ]                                # the app's answer
                w = kf.put(0, F[U_KIND], Z.kind)
                w = kf.put(w, F[U_MODE], Z.rmode)
                w = kf.put(w, F[U_ID], Z.rid)
                kf.seal(m, buf, w, Z.ctr[M_REQ], True)
                _send(Z, M_REQ)
                ks.protect(m, SEC[S_REQ_TX], buf, ctx, msg, tag16, length)
                _log(Z, M_REQ, m, buf, log_id, log_dlc, log_data)
                if (ken.receive(Ea, M, F, ERX, ESEC, crypto, ff, ff_first, M_REQ, buf, m.dlc)
                        == ken.RX_RELEASE):
                    held = False
        Z.hpos = ken.record(Ea, I, O, hashbuf, Z.hpos, rows[ek])
        if not held:
            _log(Z, M_CMD, M[M_CMD], out[0], log_id, log_dlc, log_data)
            _plant_cmd(Z, M, F, PRX, SEC, out[0], crypto)
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
