"""The frame-driven nodes in one process: driver policies, the receive path's reactions to bad
frames, the plant's fallback without commands, and the lockstep clock."""

import numpy as np
import pytest

from firmware import params as fp
from firmware import safety
from hil.config import ConfigError, default_vehicle, load_driver_script
from hil.nodes import sil
from hil.nodes import ID, AppNode, EcuNode, LockstepClock, PlantNode, run_in_process
from hil.sim.road import constant_route
from hil.transport.codec import Codec

CFG = default_vehicle()
CODEC = Codec()


def test_script_policy_drives_the_modes():
    script = [(1.0, "choose", fp.MODE_SAFETY), (2.5, "choose", fp.MODE_COMFORT),
              (4.0, "refuse", None)]
    rep, tr = sil.run(CFG, constant_route("B", 20.0, 5.0), "auto", 1, policy="script",
                      script=script)
    mode = tr.arrays["mode"]
    t = np.arange(len(mode)) * 0.001
    assert np.all(mode[t < 1.0] == fp.MODE_PASSIVE)
    assert np.all(mode[(t > 1.11) & (t < 2.5)] == fp.MODE_SAFETY)
    assert np.all(mode[t > 2.61] == fp.MODE_COMFORT)
    assert rep["driver"]["requests"] == {"choose": 2, "refuse": 1}


def test_interactive_policy_sends_what_was_pushed():
    app = AppNode(CODEC, "interactive")
    app.push("choose", fp.MODE_SAFETY)
    rec = CODEC.encode_raw("MODE_RECOMMEND", {"RECOMMENDED_MODE": 2, "ACTIVE_MODE": 0})
    (fid, data), = app.on_frame(ID["MODE_RECOMMEND"], rec)
    d = CODEC.decode(fid, data).signals
    assert (d["REQ_KIND"], d["REQ_MODE"], d["REQ_ID"]) == (fp.REQ_CHOOSE, fp.MODE_SAFETY, 1)
    # nothing queued: the heartbeat repeats the last request
    (_, data2), = app.on_frame(ID["MODE_RECOMMEND"], rec)
    d2 = CODEC.decode(fid, data2).signals
    assert (d2["REQ_KIND"], d2["REQ_ID"]) == (fp.REQ_CHOOSE, 1) and d2["COUNTER"] == 1


def _recommend(app, rec, active, reason=0, status_frames=1):
    """``status_frames`` ECU_STATUS (10 ms each), then one MODE_RECOMMEND; the app's answer."""
    for _ in range(status_frames):
        app.on_frame(ID["ECU_STATUS"], CODEC.encode_raw("ECU_STATUS", {}))
    frame = CODEC.encode_raw("MODE_RECOMMEND", {"RECOMMENDED_MODE": rec, "ACTIVE_MODE": active,
                                                "REASON": reason, "OVERRIDE": int(reason == 1)})
    (fid, data), = app.on_frame(ID["MODE_RECOMMEND"], frame)
    d = CODEC.decode(fid, data).signals
    return d["REQ_KIND"], d["REQ_ID"]


@pytest.mark.parametrize("policy", ["auto", "refuse"])
def test_the_app_does_not_answer_again_while_the_ecu_overrides_the_drivers_mode(policy):
    # seed 6 of the vehicle family (the default car with tyre x1.3): the driver accepted D,
    # 15 ms later road holding put the car in safety, and the app accepted D again at once:
    # a second request within request_min_s, which the ECU reports as spam (FAULT_RATE)
    app = AppNode(CODEC, policy, reaction_ticks=1000)
    D, C = fp.MODE_COMPREHENSIVE, fp.MODE_SAFETY
    assert _recommend(app, D, C, status_frames=1)[1] == 0         # shown, not yet for 1 s
    kind, rid = _recommend(app, D, C, status_frames=100)
    assert rid == 1 and kind == (fp.REQ_ACCEPT if policy == "auto" else fp.REQ_REFUSE)
    if policy == "auto":
        assert _recommend(app, D, D)[1] == 1                      # the ECU took it
    for reason in (1, 2):                                         # road holding, a fault
        for _ in range(30):
            assert _recommend(app, D, C, reason=reason, status_frames=10)[1] == 1
    # the override ends and the car is back in the driver's mode: still nothing to answer
    assert _recommend(app, D, D if policy == "auto" else C, status_frames=10)[1] == 1


def test_unknown_policy_is_refused():
    with pytest.raises(ValueError, match="unknown driver policy"):
        AppNode(CODEC, "sporty")


def _bench(seconds=2.0):
    p = sil.ecu_params(CFG, "comfort")
    plant = PlantNode(CFG, constant_route("B", 20.0, seconds), 1, CODEC)
    ecu_node = EcuNode(p, CODEC)
    app = sil.app_node(CODEC, "comfort", p.dt_s)
    return plant, ecu_node, app


def test_a_corrupted_sensor_frame_sends_the_ecu_fail_safe_at_once():
    plant, ecu_node, app = _bench()
    bad_at = 1000
    nodes = (plant, ecu_node, app)
    while not plant.done:
        frames = plant.emit()
        if plant.k == bad_at:
            fid, data = frames[-1]
            frames[-1] = (fid, bytes([data[0] ^ 1]) + data[1:])   # CHECKSUM now wrong
        queue = [(plant, f) for f in frames]
        while queue:
            src, (fid, data) = queue.pop(0)
            for node in nodes:
                if node is not src:
                    queue += [(node, r) for r in node.on_frame(fid, data)]
            while ecu_node.ready():
                queue += [(ecu_node, f) for f in ecu_node.tick()]
        plant.step()
    faults = ecu_node.trace()["faults"]
    duty = plant.trace()["duty"]
    assert faults[bad_at] & safety.FAULT_CHECKSUM
    assert duty[bad_at] == 0.0 and np.all(duty[bad_at:bad_at + 50] == 0.0)   # fail-safe
    assert np.any(duty[bad_at + 60:] != 0.0)                                  # and recovered
    # the corrupted frame is a lost frame: the next one shows the COUNTER gap
    assert ecu_node.summary()["frame_faults"] == {"PLANT_SENSORS:checksum": 1,
                                                  "PLANT_SENSORS:counter": 1}
    assert faults[bad_at + 1] & safety.FAULT_COUNTER


def test_the_plant_falls_back_to_passive_without_commands():
    plant, ecu_node, app = _bench(2.0)
    plant.n = 1000
    run_in_process(plant, ecu_node, app)
    assert plant.fallback_ticks == 0 and plant.missed_cmds == 0
    plant.n += 10
    for _ in range(10):          # the ECU falls silent
        plant.emit()
        plant.step()
    assert plant.missed_cmds == 10
    assert plant.fallback_ticks == 10 - plant.cmd_timeout_ticks
    assert np.all(plant.trace()["duty"][-(10 - plant.cmd_timeout_ticks):] == 0.0)


def test_the_ecu_ignores_truth_and_flags_unknown_ids():
    _, ecu_node, _ = _bench()
    ecu_node.on_frame(ID["SIM_TRUTH"], bytes(8))
    assert ecu_node.link_faults == 0
    ecu_node.on_frame(0x7FF, bytes(8))
    assert ecu_node.link_faults & safety.FAULT_UNKNOWN_ID


def test_lockstep_clock():
    c = LockstepClock(0.001)
    stamps = [c.stamp(f) for f in (ID["PLANT_SENSORS"], ID["ACTUATOR_CMD"], ID["PLANT_SENSORS"],
                                   ID["MODE_RECOMMEND"], ID["DRIVER_REQUEST"], ID["ACTUATOR_CMD"])]
    assert stamps == [0.0, 0.000001, 0.001, 0.001001, 0.001002, 0.001003]


def test_driver_script_files(tmp_path):
    good = tmp_path / "g.toml"
    good.write_text('[[request]]\nt_s = 2.0\nkind = "accept"\n'
                    '[[request]]\nt_s = 1.0\nkind = "choose"\nmode = "safety"\n')
    assert load_driver_script(good) == [(1.0, "choose", fp.MODE_SAFETY), (2.0, "accept", None)]
    for text, key in (('[[request]]\nkind = "accept"\n', "request[0].t_s"),
                      ('[[request]]\nt_s = -1\nkind = "accept"\n', "request[0].t_s"),
                      ('[[request]]\nt_s = 1\nkind = "maybe"\n', "request[0].kind"),
                      ('[[request]]\nt_s = 1\nkind = "choose"\n', "request[0].mode"),
                      ('[[request]]\nt_s = nan\nkind = "refuse"\n', "request[0].t_s"),
                      ('[[request]]\nt_s = 1\nkind = "refuse"\nspeed = 3\n', "request[0].speed"),
                      ("title = 1\n", "title"), ("", "[[request]]"), ("[[request", "invalid TOML")):
        bad = tmp_path / "b.toml"
        bad.write_text(text)
        with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
            load_driver_script(bad)


def test_every_command_names_the_sensor_frame_it_answers():
    """ACTUATOR_CMD.SENSOR_SEQ = the answered PLANT_SENSORS COUNTER modulo 4 (a tick without a
    sensor frame: the next expected one), and the plant recognises the answer to its latest
    frame (realtime pacing steps on it)."""
    frames = []
    sil.run(CFG, constant_route("B", 20.0, 0.5), "comfort", 1,
            on_frame=lambda fid, data: frames.append((fid, data)))
    seq, n = None, 0
    for fid, data in frames:
        d = CODEC.decode(fid, data, scaling=False).signals
        if fid == ID["PLANT_SENSORS"]:
            seq = d["COUNTER"] & 3
        elif fid == ID["ACTUATOR_CMD"]:
            assert d["SENSOR_SEQ"] == seq
            n += 1
    assert n == 500
    plant = PlantNode(CFG, constant_route("B", 20.0, 1.0), 1, CODEC)
    ecu_node = EcuNode(sil.ecu_params(CFG, "comfort"), CODEC, lockstep=False)

    def command():
        return next(f for f in ecu_node.tick() if f[0] == ID["ACTUATOR_CMD"])

    for fid, data in plant.emit():
        ecu_node.on_frame(fid, data)
    plant.on_frame(*command())
    assert plant.answered()             # the answer to the frame just sent
    plant.step()
    plant.emit()                        # a new frame; the ECU has not answered it yet
    assert not plant.answered()
    ecu_node.timer_tick()               # ... and it never arrives: the ECU's timer ticks
    plant.on_frame(*command())
    assert plant.answered()             # a timer tick answers the expected frame


def test_lockstep_steps_only_on_a_valid_command_for_this_tick():
    """A flood of ACTUATOR_CMD-ID garbage, a bad CHECKSUM, a repeated COUNTER and a valid
    command answering another sensor frame never end the plant's tick; each is counted; the
    invalid ones are never applied; the ECU's real command ends the tick."""
    plant = PlantNode(CFG, constant_route("B", 20.0, 1.0), 1, CODEC)
    ecu_node = EcuNode(sil.ecu_params(CFG, "comfort"), CODEC, lockstep=False)
    for fid, data in plant.emit():
        ecu_node.on_frame(fid, data)
    cmd_id, cmd = next(f for f in ecu_node.tick() if f[0] == ID["ACTUATOR_CMD"])
    spec = CODEC.specs[cmd_id]
    for junk in (bytes(8), b"\xff" * 8, bytes(3), bytes(range(8))):
        plant.on_frame(cmd_id, junk)
    forged = bytearray(cmd)
    forged[spec.checksum_byte] ^= 0x01
    plant.on_frame(cmd_id, bytes(forged))
    assert not plant.ready() and plant.cmd_tick == -1
    assert plant.bad_cmd_frames == 5
    # a valid command for another sensor frame (SENSOR_SEQ + 1): applied-as-latest in
    # realtime, but it does not answer this tick
    seq = plant.tx.counters["PLANT_SENSORS"] & 3
    other = CODEC.encode_raw("ACTUATOR_CMD", {"DUTY": 30000, "REGEN": 0, "ENABLE": 1,
                                              "SENSOR_SEQ": seq}, 0)
    plant.on_frame(cmd_id, other)
    assert not plant.ready() and plant.stale_cmd_frames == 1
    plant.on_frame(cmd_id, cmd)          # COUNTER 0 again: a repeat, invalid
    assert not plant.ready() and plant.bad_cmd_frames == 6
    # a fresh plant gets the real command: valid and answering, the tick ends
    plant = PlantNode(CFG, constant_route("B", 20.0, 1.0), 1, CODEC)
    plant.emit()
    plant.on_frame(cmd_id, cmd)
    assert plant.ready() and plant.bad_cmd_frames == 0 and plant.cmd_tick == 0
