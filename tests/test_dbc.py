"""The DBC, the codec and the frame-validity code (issue: CAN hardware-in-the-loop, part 1)."""

import math

import canmatrix.formats
import numpy as np
import pytest

from firmware import safety
from hil.sim.road import MAX_SPEED_MPS
from hil.transport import secoc
from hil.transport.codec import DBC_PATH, Codec, declared_raw_range, raw_range, to_raw
from tools.busload import bus_load

CODEC = Codec()
SAFETY_RELEVANT = ("ACTUATOR_CMD", "PLANT_SENSORS", "VEHICLE_SPEED", "ECU_STATUS",
                   "MODE_RECOMMEND", "DRIVER_REQUEST")


def test_dbc_loads_in_cantools_and_canmatrix_and_follows_conventions():
    cm = canmatrix.formats.loadp_flat(str(DBC_PATH))
    assert {f.name for f in cm.frames} == {m.name for m in CODEC.db.messages}
    for m in CODEC.db.messages:
        assert m.name == m.name.upper(), m.name
        # every message is cyclic, except the event-only simulation tick of fault injection
        # and the diagnostic (UDS, XCP) requests and responses
        event = m.dbc.attributes["GenMsgSendType"].value == "Event" \
            if "GenMsgSendType" in m.dbc.attributes else False
        assert bool(m.cycle_time) != event, m.name
        assert not event or m.name in ("SIM_TICK", "DIAG_REQUEST", "DIAG_RESPONSE", "XCP_CMD",
                                        "XCP_RES"), m.name
        for s in m.signals:
            assert s.name == s.name.upper() and s.byte_order == "little_endian"
        if m.name in SAFETY_RELEVANT:
            names = [s.name for s in m.signals]
            if m.name in secoc.SECURED:     # E2E, then the SecOC trailer (byte-aligned)
                assert names[-4:] == ["COUNTER", "CHECKSUM", "FRESHNESS", "MAC"], m.name
                secoc.layout(CODEC, m.name)
            else:
                assert names[-2:] == ["COUNTER", "CHECKSUM"], m.name
            sig = {s.name: s for s in m.signals}
            assert sig["COUNTER"].length == 4 and sig["CHECKSUM"].length == 8
    # truth lives in its own message, which the ECU does not receive
    truth = CODEC.message("SIM_TRUTH")
    assert all("ECU" not in s.receivers for s in truth.signals)


def test_every_signal_round_trips_over_its_full_range():
    """Inside the declared [minimum, maximum]: decoded as encoded. Outside it (but inside the
    raw range): the frame is rejected with the RANGE fault."""
    rng = np.random.default_rng(0)
    n_out = 0
    for m in CODEC.db.messages:
        for sig in m.signals:
            if sig.name in ("COUNTER", "CHECKSUM"):
                continue
            lo, hi = raw_range(sig)
            dlo, dhi = declared_raw_range(sig)
            raws = {lo, hi, dlo, dhi, 0 if lo <= 0 <= hi else lo,
                    *rng.integers(lo, hi, 50, endpoint=True).tolist()}
            for raw in raws:
                phys = raw * sig.scale + sig.offset
                data = CODEC.encode_raw(m.name, {sig.name: raw}, counter=5)
                dec = CODEC.decode(m.frame_id, data)
                if not dlo <= raw <= dhi:
                    n_out += 1
                    assert not dec.ok and dec.faults == safety.FAULT_RANGE, (m.name, sig.name)
                    continue
                assert dec.ok, (m.name, sig.name)
                assert dec.signals[sig.name] == pytest.approx(phys, abs=1e-9 * max(1.0, abs(phys)))
                assert CODEC.encode(m.name, {sig.name: phys}, counter=5) == data
            # the physical encoder saturates at the declared range
            for phys, raw in ((sig.maximum, dhi), (sig.minimum, dlo)):
                if phys is not None:
                    big = phys + (1 if raw == dhi else -1) * 1e3 * sig.scale
                    assert CODEC.encode(m.name, {sig.name: big}) == \
                        CODEC.encode_raw(m.name, {sig.name: raw}), (m.name, sig.name)
    assert n_out > 0


def test_route_speed_limit_is_the_speed_signal_range():
    assert CODEC.message("VEHICLE_SPEED").get_signal_by_name("SPEED").maximum == MAX_SPEED_MPS


def test_encode_rounds_half_away_from_zero_and_saturates():
    duty = CODEC.message("ACTUATOR_CMD").get_signal_by_name("DUTY")
    q = duty.scale
    assert to_raw(duty, 2.5 * q) == 3 and to_raw(duty, -2.5 * q) == -3
    assert to_raw(duty, 1.5 * q) == 2 and to_raw(duty, -1.5 * q) == -2    # not to even
    assert to_raw(duty, 5.0) == 32767 and to_raw(duty, -5.0) == -32768     # saturate
    assert to_raw(duty, math.inf) == 32767 and to_raw(duty, math.nan) == 0
    speed = CODEC.message("VEHICLE_SPEED").get_signal_by_name("SPEED")
    assert to_raw(speed, -1.0) == 0 and to_raw(speed, 1e6) == 7000     # declared maximum
    assert to_raw(speed, 0.005) == 1 and to_raw(speed, 0.00499) == 0


def test_crc8_sae_j1850_check_value():
    assert safety.crc8(b"123456789") == 0x4B


def test_checksum_counter_dlc_and_unknown_ids():
    m = CODEC.message("PLANT_SENSORS")
    spec = CODEC.specs[m.frame_id]
    st = safety.RxState()
    frames = [CODEC.encode("PLANT_SENSORS", {"BODY_ACCEL_RAW": 100 + k}, counter=k % 16) for k in range(20)]
    assert all(CODEC.decode(m.frame_id, f, st, k).ok for k, f in enumerate(frames))
    assert st.valid
    bad = bytearray(CODEC.encode("PLANT_SENSORS", {}, counter=4))
    bad[0] ^= 0x01                                               # corrupted payload
    d = CODEC.decode(m.frame_id, bytes(bad), st, 20)
    assert not d.ok and d.faults & safety.FAULT_CHECKSUM and not st.valid
    assert CODEC.decode(m.frame_id, frames[0][:7]).faults & safety.FAULT_DLC
    assert CODEC.decode(0x7FF, frames[0]).faults & safety.FAULT_UNKNOWN_ID
    # counter repeat and jump
    st = safety.RxState()
    for k, c in enumerate((1, 2, 3)):
        assert safety.check_frame(spec, st, safety.seal(spec, frames[0], c), k)
    assert not safety.check_frame(spec, st, safety.seal(spec, frames[0], 3), 3)
    assert st.faults & safety.FAULT_COUNTER
    assert not safety.check_frame(spec, st, safety.seal(spec, frames[0], 9), 4)
    # the same message ID protects against masquerading: another ID, same payload, fails
    other = CODEC.specs[CODEC.message("ECU_STATUS").frame_id]
    assert safety.checksum_of(other, frames[0]) != frames[0][spec.checksum_byte]


def test_validity_hysteresis_and_timeout():
    spec = safety.FrameSpec(msg_id=0x100, dlc=8, counter_bit=52, checksum_byte=7,
                            timeout_ticks=3, recover_frames=4)
    st = safety.RxState()
    payload = bytes(8)
    for k in range(4):
        safety.check_frame(spec, st, safety.seal(spec, payload, k), k)
        assert st.valid == (k == 3)
    assert safety.check_timeout(spec, st, 6)
    assert not safety.check_timeout(spec, st, 7) and not st.valid
    assert st.faults & safety.FAULT_TIMEOUT


def test_bus_load_from_cycle_times():
    o = bus_load(500_000.0)
    assert 0.0 < o["load"] < 0.8
    names = {r["message"] for r in o["messages"]}
    assert {"ACTUATOR_CMD", "PLANT_SENSORS"} <= names
    # an 8-byte frame at 1 kHz: 47 + 64 + 24 stuff bits = 135 bits -> 27 % of 500 kbit/s
    row = next(r for r in o["messages"] if r["message"] == "PLANT_SENSORS")
    assert row["bits_per_frame"] == 135 and row["load"] == pytest.approx(0.27)


def test_own_packer_equals_cantools_on_random_frames():
    """The codec packs and unpacks signals itself (faster); cantools is the reference."""
    import random

    rnd = random.Random(1)
    for m in CODEC.db.messages:
        for _ in range(300):
            raw = {s.name: rnd.randint(*declared_raw_range(s)) for s in m.signals}
            ours = CODEC.encode_raw(m.name, raw, raw.get("COUNTER", 0))
            ref = safety.seal(CODEC.specs[m.frame_id],
                              m.encode({**raw, **{k: 0 for k in ("COUNTER", "CHECKSUM")
                                                  if k in raw}}, scaling=False, strict=False),
                              raw.get("COUNTER", 0))
            assert ours == ref, m.name
            for scaling in (False, True):
                got = CODEC.decode(m.frame_id, ours, scaling=scaling).signals
                want = m.decode(ours, decode_choices=False, scaling=scaling)
                assert got == want and all(type(got[k]) is type(want[k]) for k in got), m.name


def test_positional_packer_and_unpacker_equal_encode_raw_and_decode():
    """Codec.packer/unpacker (the per-tick frames, by position) give the bytes of encode_raw
    and the values, faults and receiver state of decode, on valid frames, on corrupted ones
    (CHECKSUM, DLC, COUNTER) and on values outside the declared range."""
    import random

    rnd = random.Random(2)
    seen = set()
    for m in CODEC.db.messages:
        names = tuple(s.name for s in m.signals if s.name not in ("COUNTER", "CHECKSUM"))
        pack = CODEC.packer(m.name, names)
        every = tuple(s.name for s in m.signals)
        unpack = CODEC.unpacker(m.name, every)
        st_ref, st_pos = safety.RxState(), safety.RxState()
        for k in range(200):
            # raw values beyond the raw range too (both saturate), some outside the declared
            raw = {s.name: rnd.randint(raw_range(s)[0] - 2, raw_range(s)[1] + 2)
                   for s in m.signals if s.name in names}
            data = CODEC.encode_raw(m.name, raw, k % 16)
            assert pack(tuple(raw[n] for n in names), k % 16) == data, m.name
            roll = rnd.random()
            if roll < 0.1:
                data = data[:-1]                                 # DLC
            elif roll < 0.2:
                data = bytes([data[0] ^ 0x10]) + data[1:]        # CHECKSUM (or COUNTER)
            d = CODEC.decode(m.frame_id, data, st_ref, k, scaling=False)
            values, faults = unpack(data, st_pos, k)
            assert (values is not None) == d.ok and faults == d.faults, m.name
            if d.ok:
                assert values == tuple(d.signals[n] for n in every), m.name
            assert st_pos == st_ref, m.name
            seen.add(d.faults)
    # every kind of outcome was exercised
    assert {0, safety.FAULT_DLC, safety.FAULT_CHECKSUM, safety.FAULT_RANGE} <= seen
    with pytest.raises(ValueError, match="NOPE"):
        CODEC.packer("ACTUATOR_CMD", ("DUTY", "NOPE"))
    with pytest.raises(ValueError, match="NOPE"):
        CODEC.unpacker("ACTUATOR_CMD", ("NOPE",))


def test_a_big_endian_signal_is_refused_at_load(tmp_path):
    """The codec packs little-endian signals only (docs/architecture.md, Conventions): a DBC with a
    big-endian one is an error when it is loaded, never a silent slow path."""
    text = DBC_PATH.read_text().replace("SG_ SPEED : 0|13@1+", "SG_ SPEED : 7|13@0+")
    assert text != DBC_PATH.read_text()
    bad = tmp_path / "big.dbc"
    bad.write_text(text)
    with pytest.raises(ValueError, match="VEHICLE_SPEED.SPEED is big-endian"):
        Codec(bad)


def test_the_firmwares_receive_and_transmit_tables_match_the_dbc():
    """firmware.safety.RX_CHECKS and TX_MESSAGES against the DBC: every received message is
    sent by another node and has the declared period, COUNTER and CHECKSUM; the ECU transmits
    exactly the messages whose sender is ECU."""
    codec = Codec()
    db = codec.db
    ecu_tx = {m.name for m in db.messages if "ECU" in m.senders}
    assert set(safety.TX_MESSAGES) == ecu_tx
    for check in safety.RX_CHECKS:
        m = codec.message(check.message)
        assert "ECU" not in m.senders, check.message
        assert check.period_ms == codec.cycle_ms(check.message), check.message
        spec = codec.specs[m.frame_id]
        has = spec.counter_bit is not None and spec.checksum_byte is not None
        assert check.counter_checksum == has, check.message
    # every message the ECU node listens to (besides the simulation-only SIM_TICK) is checked
    from hil.nodes import ID, EcuNode
    from hil.nodes.sil import ecu_params
    from hil.config import default_vehicle

    node = EcuNode(ecu_params(default_vehicle(), "auto"), codec, key=bytes(16))
    assert node.listen - {ID["SIM_TICK"], ID["DIAG_REQUEST"], ID["XCP_CMD"]} == {
        ID[c.message] for c in safety.RX_CHECKS}
    speed = node.rx[ID["VEHICLE_SPEED"]]          # (its row of the compiled receive table)
    assert speed.timeout == 30 and speed.min_interval == 5
    assert set(node.rx) == {ID[c.message] for c in safety.RX_CHECKS}


ENUMERATED = {"ACTUATOR_CMD": ("REGEN", "ENABLE"),
              "ECU_STATUS": ("ACTIVE_MODE", "ESTIMATED_GRADE", "REASON"),
              "MODE_RECOMMEND": ("RECOMMENDED_MODE", "ESTIMATED_GRADE", "ACTIVE_MODE", "REASON",
                                 "OVERRIDE"),
              "DRIVER_REQUEST": ("REQ_KIND", "REQ_MODE"), "SIM_TRUTH": ("TRUE_GRADE",)}


def test_every_message_and_signal_is_commented_and_enumerations_have_value_tables():
    from firmware.params import GRADE_NAMES, MODE_NAMES

    for m in CODEC.db.messages:
        assert m.comment, m.name
        for s in m.signals:
            assert s.comment, (m.name, s.name)
        for name in ENUMERATED.get(m.name, ()):
            assert m.get_signal_by_name(name).choices, (m.name, name)
    mode = CODEC.message("ECU_STATUS").get_signal_by_name("ACTIVE_MODE").choices
    assert [str(mode[i]) for i in range(len(MODE_NAMES))] == list(MODE_NAMES)
    grade = CODEC.message("MODE_RECOMMEND").get_signal_by_name("ESTIMATED_GRADE").choices
    assert [str(grade[i]) for i in range(4)] == list(GRADE_NAMES) and str(grade[7]) == "unknown"


def test_the_fault_word_is_one_named_signal_per_bit_where_it_always_was():
    """ECU_STATUS: bits 0-15 of the fault word in payload bits 8-23, bits 16-17 in 48-49, each
    its own FAULT_<name> signal with a value table (the bytes of the 16-bit FAULTS word and
    SUPPLY_FAULT it replaced)."""
    from hil.transport.codec import FAULT_SIGNALS, fault_signals, fault_word

    status = CODEC.message("ECU_STATUS")
    assert set(FAULT_SIGNALS.values()) == {s.name for s in status.signals
                                           if s.name.startswith("FAULT_")}
    for bit, name in FAULT_SIGNALS.items():
        i = bit.bit_length() - 1
        sig = status.get_signal_by_name(name)
        assert (sig.start, sig.length) == ((8 + i if i < 16 else 32 + i), 1), name
        assert {int(k): str(v) for k, v in sig.choices.items()} == {0: "ok", 1: "fault"}
        data = CODEC.encode("ECU_STATUS", fault_signals(bit))
        word = int.from_bytes(data, "little") & ~(0xFF << 56) & ~(0xF << 52)
        assert word == 1 << (8 + i if i < 16 else 32 + i), name
        assert fault_word(CODEC.decode(status.frame_id, data).signals) == bit
    every = sum(FAULT_SIGNALS)
    assert fault_word(fault_signals(every)) == every


@pytest.mark.parametrize("fmt", ["arxml", "kcd", "sym"])
def test_canmatrix_exports_load_back_with_every_signal_as_in_the_dbc(tmp_path, fmt):
    from tools.dbc_export import check, export

    path = export(tmp_path, [fmt])[fmt]
    assert check(fmt, path) == []


def test_a_damaged_export_is_reported(tmp_path):
    """What the export mends, undone, is found: canmatrix's six-digit KCD slope; an ARXML
    that does not load; a missing file. And the command exits 1 on such a problem."""
    from tools.dbc_export import check, export

    paths = export(tmp_path, ["kcd", "arxml"])
    kcd = paths["kcd"].read_text()
    paths["kcd"].write_text(kcd.replace('slope="3.0517578125e-05"', 'slope="3.05176e-05"'))
    assert any("ACTUATOR_CMD.DUTY: scale" in p for p in check("kcd", paths["kcd"]))
    paths["arxml"].write_text(paths["arxml"].read_text()[:5000])
    assert "does not load" in check("arxml", paths["arxml"])[0]
    assert "not written" in check("sym", tmp_path / "none.sym")[0]


def test_dbc_export_command(tmp_path):
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "tools.dbc_export", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("checked: every message and signal as in the DBC") == 3
    bad = subprocess.run([sys.executable, "-m", "tools.dbc_export", "--formats", "dbf"],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1


def test_bus_load_counts_a_daq_as_the_xcp_slave_does():
    """tools.busload --daq decides as the slave's budget (hil.xcp.daq) does: 2 ODTs on the
    1 ms event every 4th tick fit the 80 % budget, one every tick does not."""
    from hil.transport.busload import dbc_bits_per_s
    from hil.xcp.daq import BUDGET, Daq, DaqList
    from hil.xcp.protocol import ERR_DAQ_CONFIG, XcpError
    from tools.busload import daq_spec, main

    for spec, verdict in (("1ms/4:2", "pass"), ("1ms:1", "fail"), ("10ms:5", "pass"),
                          ("10ms/2:40", "fail")):
        event, pre, odts = daq_spec(spec)
        o = bus_load(500_000.0, ((event, pre, odts),))
        slave = Daq(None, dbc_bits_per_s(), 500_000.0)
        d = DaqList(sizes=[1] * odts, event={"1ms": 0, "10ms": 1}[event], prescaler=pre)
        try:
            slave._budget([d])
            decided = "pass"
        except XcpError as exc:
            assert exc.code == ERR_DAQ_CONFIG
            decided = "fail"
        assert o["verdict"] == decided == verdict, spec
        assert (o["load"] <= BUDGET) == (verdict == "pass")
    assert main(["--daq", "1ms:1", "--json"]) == 1 and main(["--daq", "1ms/4:2", "--json"]) == 0
    for bad in ("2ms:1", "1ms/0:1", "1ms", "1ms:x"):
        with pytest.raises(ValueError, match="--daq"):
            daq_spec(bad)
