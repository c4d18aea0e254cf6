"""Only the right node commands: SecOC (profile 1) on ACTUATOR_CMD and DRIVER_REQUEST, the
key files, and the hub's sender allow-list with read-only external clients."""

import os
import stat
import subprocess
import sys
from pathlib import Path

import can
import pytest

from firmware import params as fp
from firmware import safety
from hil.config import ConfigError, default_vehicle
from hil.nodes import ID, EcuNode, PlantNode, run_in_process
from hil.nodes.sil import app_node, ecu_params
from hil.sim.road import constant_route
from hil.transport import auth, secoc
from hil.transport.bus import BusError, BusSpec, Hub, close_bus
from hil.transport.codec import Codec

ROOT = Path(__file__).resolve().parents[1]
CODEC = Codec()
CFG = default_vehicle()
KEY = bytes(range(16))


def _forged_cmd(counter: int, duty: float = 0.88, seq: int = 0) -> bytes:
    """An ACTUATOR_CMD as an attacker who has the DBC builds it: valid CRC and COUNTER, no
    key (the MAC bytes are whatever the attacker puts there)."""
    return CODEC.encode("ACTUATOR_CMD", {"DUTY": duty, "REGEN": 0, "ENABLE": 1,
                                         "SENSOR_SEQ": seq, "FRESHNESS": 7,
                                         "MAC": 0x123456}, counter)


def test_secoc_accepts_its_own_frames_and_nothing_else():
    lay = secoc.layout(CODEC, "ACTUATOR_CMD")
    tx, rx = secoc.Sender(KEY, lay), secoc.Receiver(KEY, lay)
    frames = [tx.protect(_forged_cmd(i & 0xF, 0.1)) for i in range(600)]
    assert all(len(f) == 8 for f in frames)
    spec = CODEC.specs[ID["ACTUATOR_CMD"]]
    assert all(f[spec.checksum_byte] == safety.checksum_of(spec, f) for f in frames)
    assert rx.verify(frames[0]) and rx.verify(frames[1])
    assert not rx.verify(frames[1]) and not rx.verify(frames[0])    # replays
    # 299 frames lost: the 8-bit freshness wraps, the receiver resynchronises by itself
    assert rx.verify(frames[300]) and rx.latest == 301
    assert not rx.verify(frames[299])                               # older: stale
    # a changed payload (CRC resealed: a man in the middle), another key, no key at all
    tampered = bytearray(frames[301])
    tampered[0] ^= 0x40
    tampered[spec.checksum_byte] = safety.checksum_of(spec, tampered)
    assert not rx.verify(bytes(tampered))
    other = secoc.Sender(os.urandom(16), lay)
    other.fv = 301
    assert not rx.verify(other.protect(_forged_cmd(1, 0.1)))
    assert not rx.verify(_forged_cmd(1))
    assert rx.verify(frames[301]) and rx.rejected == 6
    # more than RESYNC_WINDOWS x 256 frames lost: no longer accepted (documented limit)
    tx.fv = rx.latest + secoc.RESYNC_WINDOWS * 256
    assert not rx.verify(tx.protect(_forged_cmd(2, 0.1)))


def test_key_files(tmp_path):
    path = tmp_path / "k"
    key = secoc.write_key(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and secoc.load_key(path) == key
    with pytest.raises(FileExistsError):
        secoc.write_key(path)                    # never overwritten
    path.chmod(0o644)
    with pytest.raises(ConfigError, match="accessible to others"):
        secoc.load_key(path)
    bad = tmp_path / "bad"
    bad.write_text("abcd\n")
    bad.chmod(0o600)
    with pytest.raises(ConfigError, match="32 hex digits"):
        secoc.load_key(bad)
    with pytest.raises(ConfigError, match="no such key file"):
        secoc.load_key(tmp_path / "none")
    proc = subprocess.run([sys.executable, "-m", "hil", "keygen", str(tmp_path / "new")],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and len(secoc.load_key(tmp_path / "new")) == 16
    proc = subprocess.run([sys.executable, "-m", "hil", "keygen", str(tmp_path / "new")],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "never overwritten" in proc.stderr
    # a node without its key file refuses in one line, before it touches a bus
    proc = subprocess.run([sys.executable, "-m", "hil", "plant"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "--key-file" in proc.stderr


def _bench(seconds: float = 3.0):
    plant = PlantNode(CFG, constant_route("B", 20.0, seconds), 1, CODEC, key=KEY)
    ecu_node = EcuNode(ecu_params(CFG, "comfort"), CODEC, key=KEY)
    app = app_node(CODEC, "comfort", CFG.sim.plant_dt_s, key=KEY)
    return plant, ecu_node, app


def test_forged_and_replayed_commands_never_reach_the_plant_in_process():
    plant, ecu_node, app = _bench()
    recorded = []
    plant.n = 1500
    run_in_process(plant, ecu_node, app, on_frame=lambda fid, data: recorded.append(
        (fid, data)) if fid == ID["ACTUATOR_CMD"] else None)
    assert plant.auth_failures == 0 and plant.bad_cmd_frames == 0
    applied = (plant.cmd, plant.cmd_tick)
    rx_state = (plant.cmd_rx.last_counter, plant.cmd_auth.latest)
    # the next tick's frames are out; now the attacks, before the ECU answers
    frames = plant.emit()
    seq = (plant.tx.counters["PLANT_SENSORS"] - 1) & 3
    nxt = (plant.cmd_rx.last_counter + 1) & 0xF
    attacks = [_forged_cmd(nxt, 0.88, seq),                        # no key, right COUNTER
               recorded[700][1],                                    # replayed from this run
               recorded[-1][1]]                                     # the last one again
    for data in attacks:
        plant.on_frame(ID["ACTUATOR_CMD"], data)
    assert plant.auth_failures == 3 and not plant.ready()
    assert (plant.cmd, plant.cmd_tick) == applied                   # nothing applied
    assert (plant.cmd_rx.last_counter, plant.cmd_auth.latest) == rx_state   # state untouched
    # the ECU's real command still is accepted and ends the tick
    queue = list(frames)                 # (the bus, as run_in_process routes it)
    while queue:
        fid, data = queue.pop(0)
        for node in (ecu_node, app, plant):
            if fid not in node.ignore:
                queue += node.on_frame(fid, data)
        while ecu_node.ready():
            queue += ecu_node.tick()
    assert plant.ready() and plant.cmd_tick == plant.k and plant.auth_failures == 3


def test_a_forged_driver_request_changes_no_mode():
    plant, ecu_node, app = _bench()
    early = CODEC.encode("DRIVER_REQUEST", {"REQ_KIND": fp.REQ_CHOOSE,
                                            "REQ_MODE": fp.MODE_PASSIVE, "REQ_ID": 3,
                                            "FRESHNESS": 1, "MAC": 7}, 0)
    ecu_node.on_frame(ID["DRIVER_REQUEST"], early)          # before any genuine one
    rx = ecu_node.rx[ID["DRIVER_REQUEST"]]
    assert rx.last_counter == -1 and ecu_node.frame_faults == {"DRIVER_REQUEST:auth": 1}
    plant.n = 1500
    run_in_process(plant, ecu_node, app)
    assert ecu_node.state.modes.active_mode == fp.MODE_COMFORT
    forged = CODEC.encode("DRIVER_REQUEST", {"REQ_KIND": fp.REQ_CHOOSE,
                                             "REQ_MODE": fp.MODE_PASSIVE, "REQ_ID": 9,
                                             "FRESHNESS": 1, "MAC": 0}, 5)
    assert ecu_node.on_frame(ID["DRIVER_REQUEST"], forged) == []
    assert ecu_node.frame_faults == {"DRIVER_REQUEST:auth": 2}    # no COUNTER fault either
    plant.n = 2500
    run_in_process(plant, ecu_node, app)
    assert ecu_node.state.modes.active_mode == fp.MODE_COMFORT
    assert ecu_node.state.modes.user_mode == fp.MODE_COMFORT


def _client(url: str, node=None, secret=None, **kw):
    old = os.environ.get(auth.SECRET_ENV)
    try:
        if secret:
            os.environ[auth.SECRET_ENV] = secret
        return BusSpec("remote", url).open(node=node, **kw)
    finally:
        if old is None:
            os.environ.pop(auth.SECRET_ENV, None)
        else:
            os.environ[auth.SECRET_ENV] = old


def _send(bus, fid: int, data: bytes = bytes(8)) -> None:
    bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))


@pytest.mark.hil
def test_the_hub_relays_each_node_its_own_messages_and_nobody_else(tmp_path):
    secret = os.urandom(16).hex()
    log = tmp_path / "hub.log"
    with Hub(secret=secret, log_path=log) as hub:
        ecu = _client(hub.url, "ECU", secret)
        plant = _client(hub.url, "PLANT", secret)
        viewer = _client(hub.url)                              # can.viewer, can.logger...
        try:
            _send(ecu, ID["ACTUATOR_CMD"])                     # the ECU's: relayed
            assert plant.recv(2.0).arbitration_id == ID["ACTUATOR_CMD"]
            assert viewer.recv(2.0).arbitration_id == ID["ACTUATOR_CMD"]
            _send(ecu, ID["PLANT_SENSORS"])                    # the plant's: dropped
            _send(viewer, ID["ACTUATOR_CMD"])                  # read-only: dropped
            _send(viewer, ID["SIM_TICK"], bytes(1))
            _send(plant, ID["SIM_TICK"], bytes(1))             # SIM is the plant's
            got = viewer.recv(2.0)
            assert got.arbitration_id == ID["SIM_TICK"]
            assert plant.recv(0.5) is None and viewer.recv(0.3) is None
            with pytest.raises(BusError, match="refused: disconnected: authentication as "
                                               "'ECU' failed"):
                _client(hub.url, "ECU", os.urandom(16).hex())    # a wrong secret
        finally:
            for b in (ecu, plant, viewer):
                close_bus(b)
    text = log.read_text()
    assert "ECU may not send 0x100" in text and "(read-only) may not send 0x80" in text
    assert "authentication as 'ECU' failed" in text
    # --allow-external-tx opens the bus to anyone, on purpose
    with Hub(secret=secret, allow_external_tx=True) as hub:
        viewer, ecu = _client(hub.url), _client(hub.url, "ECU", secret)
        try:
            _send(viewer, ID["ACTUATOR_CMD"])
            assert ecu.recv(2.0).arbitration_id == ID["ACTUATOR_CMD"]
        finally:
            close_bus(viewer)
            close_bus(ecu)


def test_sim_tick_is_obeyed_in_lockstep_only():
    tick = CODEC.encode_raw("SIM_TICK", {"TICK": 0})
    for lockstep in (True, False):
        ecu_node = EcuNode(ecu_params(CFG, "comfort"), CODEC, lockstep=lockstep, key=KEY)
        ecu_node.on_frame(ID["SIM_TICK"], tick)
        assert ecu_node.ready() is lockstep


def _attack_run(tmp_path, *extra):
    """A lockstep bench run with an outside process on its hub that sends a forged
    ACTUATOR_CMD (88 % duty, valid CRC and COUNTER) every millisecond, replays genuine
    commands it heard on the bus, and sends a forged DRIVER_REQUEST (choose passive) every
    100 ms, the way the issue's attack did."""
    import json
    import time

    sup = subprocess.Popen([sys.executable, "-m", "hil", "run", "--out", str(tmp_path),
                            "--route", str(ROOT / "tests" / "golden" / "routes" / "b20.toml"),
                            "--mode", "comfort", "--duration", "30", "--json", *extra],
                           cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = sup.stderr.readline().split()[2]            # "bus: remote ws://127.0.0.1:PORT/ ..."
    deadline = time.monotonic() + 120
    log = tmp_path / "bus.log"            # the plant drives once sensor frames are logged
    while not (log.exists() and log.stat().st_size > 20_000):
        assert time.monotonic() < deadline and sup.poll() is None, "the bench did not start"
        time.sleep(0.05)
    attacker = _client(url)
    sent = {"cmd": 0, "req": 0, "replayed": 0}
    try:
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end and sup.poll() is None:
            _send(attacker, ID["ACTUATOR_CMD"], _forged_cmd(sent["cmd"] & 0xF))
            sent["cmd"] += 1
            # and a genuine command heard on the bus (a read-only client hears all), replayed
            heard = attacker.recv(0)
            while heard is not None and heard.arbitration_id != ID["ACTUATOR_CMD"]:
                heard = attacker.recv(0)
            if heard is not None and sent["cmd"] % 10 == 0:
                _send(attacker, ID["ACTUATOR_CMD"], bytes(heard.data))
                sent["replayed"] += 1
            if sent["cmd"] % 100 == 0:
                _send(attacker, ID["DRIVER_REQUEST"], CODEC.encode("DRIVER_REQUEST", {
                    "REQ_KIND": fp.REQ_CHOOSE, "REQ_MODE": fp.MODE_PASSIVE, "REQ_ID": 9,
                    "FRESHNESS": 3, "MAC": 1}, sent["req"] & 0xF))
                sent["req"] += 1
            time.sleep(0.001)
    finally:
        close_bus(attacker)
    out, err = sup.communicate(timeout=300)
    return sup.returncode, json.loads(out), err, sent


@pytest.mark.hil
def test_an_outside_sender_on_the_bench_hub_reaches_nothing(tmp_path):
    import numpy as np

    code, rep, err, sent = _attack_run(tmp_path)
    assert sent["cmd"] > 1000
    assert code == 0 and rep["verdict"] == "pass", err[-2000:]
    assert rep["plant_auth_failures"] == rep["plant_bad_cmd_frames"] == 0
    assert "(read-only) may not send 0x80: dropped" in (tmp_path / "hub.log").read_text()
    mode = np.load(tmp_path / "ecu.npz")["mode"]
    assert np.all(mode[200:] == fp.MODE_COMFORT)


@pytest.mark.hil
def test_with_external_tx_allowed_secoc_still_rejects_every_forgery(tmp_path):
    import numpy as np

    code, rep, err, sent = _attack_run(tmp_path, "--allow-external-tx")
    assert sent["replayed"] > 0          # forged and replayed commands both
    # every forged command reached the plant and was rejected there, every forged request
    # the ECU; none was applied; the verdict says the run was attacked
    assert code == 1 and rep["verdict"] == "fail"
    failed = {c["name"] for c in rep["checks"] if not c["ok"]}
    assert "plant_auth_failures" in failed and "frame_faults" in failed
    # (how much of the attack met the run depends on the host's speed: the run may end first)
    assert 0 < rep["plant_auth_failures"] <= sent["cmd"] + sent["replayed"]
    assert 0 < rep["frame_faults"].get("DRIVER_REQUEST:auth", 0) <= sent["req"]
    assert set(rep["frame_faults"]) == {"DRIVER_REQUEST:auth"}   # the real ones untouched
    assert rep["plant_bad_cmd_frames"] == 0 and rep["plant_fallback_ticks"] == 0
    mode = np.load(tmp_path / "ecu.npz")["mode"]
    assert np.all(mode[200:] == fp.MODE_COMFORT)


@pytest.mark.hil
def test_the_run_secret_and_key_never_go_on_a_command_line(tmp_path):
    """The hub's secret reaches the hub and the nodes in their environment only; the SecOC
    key in a 0600 file whose path (not the key) is on the nodes' command lines."""
    import signal
    import time

    from tests.procutil import children, cmdline

    sup = subprocess.Popen([sys.executable, "-m", "hil", "run", "--out", str(tmp_path),
                            "--route", str(ROOT / "tests" / "golden" / "routes" / "b20.toml"),
                            "--mode", "comfort"], cwd=ROOT, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        kids: dict = {}
        while time.monotonic() < deadline:
            kids = {p: cmdline(p) for p in children(sup.pid)}
            if sum((" plant " in c) + (" ecu " in c) + (" app " in c) + ("hil.hub" in c)
                   for c in kids.values()) == 4:
                break
            time.sleep(0.1)
        assert len(kids) >= 4, kids
        secrets = set()
        for pid in kids:
            env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
            secrets |= {e.split(b"=", 1)[1].decode() for e in env
                        if e.startswith(auth.SECRET_ENV.encode() + b"=")}
        assert len(secrets) == 1                       # one per run, handed to all four
        secret, = secrets
        key = (tmp_path / secoc.KEY_FILE_NAME).read_text().strip()
        assert stat.S_IMODE((tmp_path / secoc.KEY_FILE_NAME).stat().st_mode) == 0o600
        for line in (*kids.values(), cmdline(sup.pid)):
            assert secret not in line and key not in line, line
    finally:
        sup.send_signal(signal.SIGINT)
        sup.wait(60)
