"""Property tests (deterministic, bounded): bad input never escapes as an exception."""

import math
import string

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware import safety
from hil.config import ConfigError, load_vehicle
from hil.sim.road import load_route
from hil.transport.codec import Codec

CODEC = Codec()
FUZZ = settings(max_examples=300, derandomize=True, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
KNOWN_IDS = sorted(CODEC.specs)


@FUZZ
@given(frame_id=st.one_of(st.sampled_from(KNOWN_IDS), st.integers(0, 0x7FF)),
       data=st.binary(min_size=0, max_size=64))
def test_codec_decode_never_raises(frame_id, data):
    d = CODEC.decode(frame_id, data)
    assert d.ok in (True, False)
    if d.ok:
        assert frame_id in CODEC.specs and len(data) == CODEC.specs[frame_id].dlc
    else:
        assert d.faults


@FUZZ
@given(frame_id=st.sampled_from(KNOWN_IDS), data=st.binary(min_size=0, max_size=16),
       ticks=st.lists(st.integers(0, 10_000), min_size=1, max_size=5))
def test_safety_checks_never_raise(frame_id, data, ticks):
    spec = safety.FrameSpec(**{**CODEC.specs[frame_id].__dict__, "timeout_ticks": 10,
                               "recover_frames": 3})
    rx = safety.RxState()
    intact = len(data) == spec.dlc and (spec.checksum_byte is None or
                                         data[spec.checksum_byte] == safety.checksum_of(spec, data))
    for t in sorted(ticks):
        before = rx.valid
        used = safety.check_frame(spec, rx, data, t)
        assert intact or (not used and not rx.valid and rx.good_run == 0)  # a broken frame: never
        assert rx.valid == before or used or not rx.valid   # valid again only on a used frame
        safety.check_timeout(spec, rx, t + 5)
        assert not rx.valid or rx.good_run >= spec.recover_frames    # after enough good frames


@FUZZ
@given(name=st.sampled_from([m.name for m in CODEC.db.messages]),
       values=st.dictionaries(st.sampled_from(["DUTY", "SPEED", "BODY_ACCEL_RAW", "FAULT_TIMEOUT",
                                               "ROAD_EST", "REQ_MODE", "STORED_ENERGY"]),
                              st.floats(allow_nan=True, allow_infinity=True) | st.integers(-2**70, 2**70)),
       counter=st.integers(-100, 100))
def test_codec_encode_saturates_instead_of_raising(name, values, counter):
    data = CODEC.encode(name, values, counter)
    m = CODEC.message(name)
    assert len(data) == m.length
    d = CODEC.decode(m.frame_id, data)
    assert d.ok


TOML_VALUES = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(lambda x: repr(x) if math.isfinite(x) else ("nan" if math.isnan(x) else ("inf" if x > 0 else "-inf"))),
                        st.integers(-10**6, 10**6).map(str), st.sampled_from(['"B"', '"Z"', "true", "[1, 2]", '"x"']))
KEYS = ["sprung_mass_kg", "unsprung_mass_kg", "spring_stiffness_n_per_m", "damping_n_s_per_m",
        "tire_stiffness_n_per_m", "bogus_key"]


@FUZZ
@given(pairs=st.lists(st.tuples(st.sampled_from(KEYS), TOML_VALUES), max_size=7),
       garbage=st.text(alphabet=string.printable, max_size=20), tables=st.sampled_from(["[vehicle]", "[vehicle", "", "[actuator]"]))
def test_random_vehicle_toml_loads_or_fails_clearly(tmp_path_factory, pairs, garbage, tables):
    path = tmp_path_factory.mktemp("v") / "car.toml"
    body = "\n".join(f"{k} = {v}" for k, v in dict(pairs).items())
    path.write_text(f"{tables}\n{body}\n" + (f"# {garbage}" if "\n" not in garbage else ""))
    try:
        cfg = load_vehicle(path)
    except ConfigError as exc:
        msg = str(exc)
        assert "\n" not in msg and str(path) in msg
    else:
        assert all(math.isfinite(v) and v > 0 for v in cfg.vehicle.__dict__.values())


SEG_KEYS = ["grade", "gq_m3", "length_m", "speed_mps", "slope"]


@FUZZ
@given(segments=st.lists(st.lists(st.tuples(st.sampled_from(SEG_KEYS), TOML_VALUES), max_size=5),
                         max_size=4),
       road=st.sampled_from(["", '[road]\nconvention = "paper"\n', '[road]\ndx_m = 5.0\n', "[road]\nx = 1\n"]))
def test_random_route_toml_loads_or_fails_clearly(tmp_path_factory, segments, road):
    path = tmp_path_factory.mktemp("r") / "route.toml"
    parts = [road]
    for seg in segments:
        parts.append("[[segment]]\n" + "\n".join(f"{k} = {v}" for k, v in dict(seg).items()))
    path.write_text("\n".join(parts) + "\n")
    try:
        r = load_route(path)
    except ConfigError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
    else:
        assert r.segments and all(s.length_m > 0 and 0 < s.speed_mps <= 70 for s in r.segments)


# -- the nodes' receive paths: a random frame stream between valid sensor frames ---------------

_PARAMS = []


def _nodes():
    from hil.config import default_vehicle
    from hil.nodes import AppNode, EcuNode, PlantNode
    from hil.sim.road import constant_route
    from hil.nodes.sil import ecu_params

    cfg = default_vehicle()
    if not _PARAMS:
        _PARAMS.append(ecu_params(cfg, "comfort"))
    plant = PlantNode(cfg, constant_route("B", 20.0, 1.0), 1, CODEC)
    return plant, EcuNode(_PARAMS[0], CODEC), AppNode(CODEC, "auto")


FRAMES = st.lists(st.tuples(st.one_of(st.sampled_from(KNOWN_IDS), st.integers(0, 0x7FF)),
                            st.binary(min_size=0, max_size=12)), max_size=12)


@settings(max_examples=200, derandomize=True, deadline=None)
@given(junk=st.lists(FRAMES, min_size=1, max_size=6))
def test_random_frames_never_crash_a_node_and_never_drive_the_bridge_blind(junk):
    from firmware.safety import SAFETY_RELEVANT

    plant, ecu_node, app = _nodes()
    for burst in junk:
        frames = plant.emit()
        for fid, data in [*burst, *frames]:
            for node in (ecu_node, app, plant):
                node.on_frame(fid, data)
        while ecu_node.ready():
            for fid, data in ecu_node.tick():
                plant.on_frame(fid, data)
                app.on_frame(fid, data)
            ecu_node.record()
            last = {k: v[-1] for k, v in ecu_node.trace().items()}
            if last["faults"] & SAFETY_RELEVANT:
                assert not last["enable"]
        if plant.ready():
            plant.step()
