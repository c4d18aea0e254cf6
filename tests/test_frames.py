"""The compiled frames and SecOC (hil/kernels/frames.py, hil/kernels/secoc.py) against the
reference: hil.transport.codec's packing and decoding, firmware.safety's receive checks and hil.transport.secoc's
profile 1, on random values, corrupted frames, replays and losses."""

import math

import numba
import numpy as np
import pytest

from firmware import safety
from hil.kernels import frames as kf
from hil.kernels import secoc as ks
from hil.kernels.cmac import Cmac
from hil.transport import secoc
from hil.transport.codec import Codec, to_raw

CODEC = Codec()
NAMES = tuple(m.name for m in CODEC.db.messages)
USES = tuple((m.name, s.name) for m in CODEC.db.messages for s in m.signals
             if s.name not in ("COUNTER", "CHECKSUM"))
M, F = CODEC.frame_tables(NAMES, USES)
ROWS = {u: i for i, u in enumerate(USES)}


@numba.njit
def _pack(M, F, mi, rows, values, counter, buf):
    w = 0
    for j in range(rows.shape[0]):
        w = kf.put(w, F[rows[j]], values[j])
    kf.seal(M[mi], buf, w, counter, True)


@numba.njit
def _to_raw(F, row, value):
    return kf.to_raw(F[row], value)


@numba.njit
def _receive(M, F, mi, RX, buf, n, tick):
    return kf.receive(F, M[mi], RX[0], buf, n, tick)


@numba.njit
def _timed_out(RX, tick):
    return kf.timed_out(RX[0], tick)


def _rows(name):
    return np.array([ROWS[u] for u in USES if u[0] == name], dtype=np.int64)


def test_packing_is_the_codecs():
    rng = np.random.default_rng(1)
    for mi, name in enumerate(NAMES):
        rows = _rows(name)
        sigs = [s for s in CODEC.message(name).signals if s.name not in ("COUNTER", "CHECKSUM")]
        for _ in range(200):
            raw = {}
            for s in sigs:      # (beyond the raw range too: both saturate)
                span = 1 << s.length
                raw[s.name] = int(rng.integers(-span, 2 * span))
            counter = int(rng.integers(0, 40))
            buf = np.zeros(8, np.uint8)
            _pack(M, F, mi, rows, np.array([raw[s.name] for s in sigs], dtype=np.int64),
                  counter, buf)
            assert buf[:M[mi]["dlc"]].tobytes() == CODEC.encode_raw(name, raw, counter), name


def test_physical_values_round_as_the_codec():
    rng = np.random.default_rng(2)
    specials = [0.0, -0.0, 0.5, -0.5, 1.5, -1.5, math.nan, math.inf, -math.inf, 1e300, -1e300]
    for (name, sig_name), row in ROWS.items():
        sig = next(s for s in CODEC.message(name).signals if s.name == sig_name)
        lo, hi = (sig.minimum or 0.0), (sig.maximum or 1.0)
        values = list(rng.uniform(lo - (hi - lo), hi + (hi - lo), 50)) + specials + [
            (i + 0.5) * sig.scale + sig.offset for i in range(-3, 3)]
        for v in values:
            assert _to_raw(F, row, float(v)) == to_raw(sig, float(v)), (name, sig_name, v)


@pytest.mark.parametrize("name", ["VEHICLE_SPEED", "PLANT_SENSORS", "MODE_RECOMMEND",
                                  "ACTUATOR_CMD", "ECU_STATUS"])
def test_receive_checks_are_the_firmwares(name):
    """A stream of good, corrupted, repeated, skipped, short, early and out-of-range frames
    through both receivers (with timeout, minimum interval and recovery): the same verdicts,
    fault bits and receiver state after every frame."""
    rng = np.random.default_rng(3)
    mi = NAMES.index(name)
    spec = CODEC.specs[CODEC.message(name).frame_id]
    spec = safety.FrameSpec(spec.msg_id, spec.dlc, spec.counter_bit, spec.checksum_byte,
                            timeout_ticks=30, recover_frames=2, min_interval_ticks=3)
    rx = kf.rx_table(1)
    rx[0]["timeout"], rx[0]["min_interval"], rx[0]["recover"] = 30, 3, 2
    st = safety.RxState()
    sigs = [s for s in CODEC.message(name).signals if s.name not in ("COUNTER", "CHECKSUM")]
    counter, tick = 0, 0
    for _ in range(3000):
        raw = {s.name: int(rng.integers(0, 1 << s.length)) for s in sigs}   # (some out of range)
        data = bytearray(CODEC.encode_raw(name, raw, counter))
        roll = rng.random()
        if roll < 0.1:
            data[int(rng.integers(len(data)))] ^= 1 << int(rng.integers(8))
        elif roll < 0.15:
            data = data[:-1]
        elif roll < 0.2:
            counter += 1                      # a frame lost
        counter += 0 if rng.random() < 0.05 else 1      # (sometimes a repeat)
        tick += int(rng.integers(0, 8))
        ref_ok = CODEC.decode(spec.msg_id, bytes(data), st, tick, scaling=False,
                              spec=spec).ok
        buf = np.zeros(8, np.uint8)
        buf[:len(data)] = np.frombuffer(bytes(data), np.uint8)
        got = _receive(M, F, mi, rx, buf, len(data), tick)
        r = rx[0]
        assert got == ref_ok
        assert (bool(r["valid"]), int(r["good_run"]), int(r["last_counter"]),
                int(r["last_rx_tick"]), int(r["faults"])) == (
            st.valid, st.good_run, st.last_counter, st.last_rx_tick, st.faults)
        if rng.random() < 0.05:
            later = tick + int(rng.integers(0, 60))
            assert _timed_out(rx, later) == (not safety.check_timeout(spec, st, later))
            assert int(rx[0]["faults"]) == st.faults and bool(rx[0]["valid"]) == st.valid


@numba.njit
def _protect(M, mi, SEC, si, buf, crypto):
    ctx, msg, tag16, length = crypto
    ks.protect(M[mi], SEC[si], buf, ctx, msg, tag16, length)


@numba.njit
def _forged(M, mi, SEC, si, buf, n, crypto):
    ctx, msg, tag16, length = crypto
    return ks.forged(M[mi], SEC[si], buf, n, ctx, msg, tag16, length)


@pytest.mark.parametrize("name", secoc.SECURED)
def test_secoc_is_hil_secocs(name):
    """Signing the same frames gives the same bytes; receiving a stream with forgeries,
    replays, losses past a window (resynchronised) and short frames gives the same verdicts
    and freshness."""
    rng = np.random.default_rng(4)
    key = bytes(rng.integers(0, 256, 16, dtype=np.uint8))
    mac = Cmac(key)
    crypto = (mac.ctx, np.zeros(32, np.uint8), mac.tag16, mac.length)
    lay = secoc.layout(CODEC, name)
    mi = NAMES.index(name)
    sec = kf.table(ks.SEC, 2)
    sec[0] = (lay.fv_byte, lay.mac_byte, 0, 0)
    sec[1] = (lay.fv_byte, lay.mac_byte, 0, 0)
    sender, receiver = secoc.Sender(key, lay), secoc.Receiver(key, lay)
    sigs = [s for s in CODEC.message(name).signals
            if s.name not in ("COUNTER", "CHECKSUM", "FRESHNESS", "MAC")]
    sent = []
    for i in range(1500):
        raw = {s.name: int(rng.integers(0, 1 << s.length)) for s in sigs}
        plain = CODEC.encode_raw(name, raw, i)
        ref = sender.protect(plain)
        buf = np.zeros(8, np.uint8)
        buf[:len(plain)] = np.frombuffer(plain, np.uint8)
        _protect(M, mi, sec, 0, buf, crypto)
        assert buf[:len(plain)].tobytes() == ref
        sent.append(ref)
        roll = rng.random()
        if roll < 0.05:
            continue                                   # lost
        if roll < 0.07:
            for _ in range(int(rng.integers(250, 1150))):  # a long loss: resync or not
                sent.append(sender.protect(plain))
                _protect(M, mi, sec, 0, buf, crypto)
            frame = sent[-1]
        elif roll < 0.12:
            frame = sent[int(rng.integers(len(sent)))]  # a replay
        elif roll < 0.17:
            b = bytearray(ref)
            b[int(rng.integers(len(b)))] ^= 1 << int(rng.integers(8))
            frame = bytes(b)                            # forged or broken
        elif roll < 0.19:
            frame = ref[:-1]
        else:
            frame = ref
        rbuf = np.zeros(8, np.uint8)
        rbuf[:len(frame)] = np.frombuffer(frame, np.uint8)
        assert _forged(M, mi, sec, 1, rbuf, len(frame), crypto) == receiver.forged(frame)
        assert int(sec[1]["fv"]) == receiver.latest
        assert int(sec[1]["rejected"]) == receiver.rejected
    assert receiver.rejected > 10
