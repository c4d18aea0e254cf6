"""C portability as a tested fact: the generated tables compile warning-free and regenerate
byte-identically; the C fixed-point control path (c/ecu_fx.c) gives the same integers as the
compiled one (firmware/fx/path.py) on every tick of a recorded trace; cantools' generated C packs
our frames to the same bytes as the Python encoder."""

import random
import re
import subprocess
import sys
from pathlib import Path

import cantools
import pytest

from calib import c_tables as tables
from calib.fx_tables import build_tables
from calib.options import DesignOptions
from firmware import params as fp
from firmware.akf import (COV_ADAPT, COV_CURRENT_UNKNOWN, COV_LIFTED, COV_RESTART,
                          COV_STROKE_UNKNOWN)
from firmware.fx.tables import Fx
from hil.config import default_vehicle
from hil.nodes import sil
from hil.sim.road import load_route
from hil.transport.codec import Codec, raw_range
from tools.c_build import (C_DIR, GEN, PARITY_S, REPLAY_SOURCES, bump_stop_trace, compile_c,
                           full_road_trace, left_out_trace, replay_sources,
                           sensor_fault_trace)
from tools.c_build import parse_cov_output, replay_cov_input
from tools.c_build import replay_input as trace_text

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- tables


def test_tables_regenerate_identically_and_match_the_committed_copy():
    a = tables.generate(default_vehicle())
    b = tables.generate(default_vehicle())
    assert a == b
    for name, text in a.items():
        committed = (GEN / name).read_text()
        assert committed == text, f"{GEN / name} is stale: run make tables and commit it"


def test_tables_name_generator_and_inputs_and_carry_no_date():
    files = tables.generate(default_vehicle())
    h = files[tables.HEADER]
    assert "do not edit" in h and "tools/tables.py" in h
    digest = re.search(r'ECU_TABLES_INPUTS_SHA256 "([0-9a-f]{64})"', h).group(1)
    assert digest == tables.inputs_digest(default_vehicle(), None, DesignOptions())
    for text in files.values():
        assert not re.search(r"\b(19|20)\d\d-\d\d-\d\d\b|__DATE__|__TIME__", text)


def test_header_compiles_warning_free(tmp_path):
    main = tmp_path / "use.c"
    main.write_text('#include "ecu_tables.h"\nint main(void) { return FX_PHI_Q31[0] != 0 '
                    '&& CONTROL_K_SAFETY_F32[0] != 0.0f ? 0 : 1; }\n')
    exe = compile_c(tmp_path / "use", [main, GEN / "ecu_tables.c"])
    assert subprocess.run([str(exe)]).returncode == 0


def test_tables_cli_check_detects_a_stale_copy(tmp_path):
    run = [sys.executable, "-m", "tools.tables", "--out", str(tmp_path)]
    assert subprocess.run(run + ["--check"], cwd=ROOT, capture_output=True).returncode == 1
    assert subprocess.run(run, cwd=ROOT, capture_output=True).returncode == 0
    assert subprocess.run(run + ["--check"], cwd=ROOT, capture_output=True).returncode == 0
    (tmp_path / tables.HEADER).write_text((tmp_path / tables.HEADER).read_text() + " ")
    res = subprocess.run(run + ["--check", "--json"], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 1 and tables.HEADER in res.stdout


def test_every_table_constant_is_its_float_to_the_precision_of_its_format():
    T = build_tables(sil.ecu_params(default_vehicle(), "auto"))
    n = 0
    for name in T.__dataclass_fields__:
        v = getattr(T, name)
        for c in (v if isinstance(v, tuple) else (v,)):
            if isinstance(c, Fx):
                n += 1
                assert abs(c.m * 2.0 ** -c.frac - c.value) <= 2.0 ** -(c.frac + 1), (name, c)
                assert abs(c.m) < 2 ** 31
                if abs(c.value) >= 1e-3:   # at least 16 significant bits
                    assert abs(c.m * 2.0 ** -c.frac / c.value - 1.0) <= 2.0 ** -16, (name, c)
    assert n > 100


# ---------------------------------------------------------------- fixed-point parity


@pytest.fixture(scope="module")
def replay_exe(tmp_path_factory):
    d = tmp_path_factory.mktemp("c")
    return compile_c(d / "trace_replay", REPLAY_SOURCES)


def assert_estimator_bit_exact(exe, rec):
    """``trace_replay --cov``: the covariance side of the filter in C (c/akf_cov.c, double)
    from the counts, q_road and the flags alone gives the Python path's float gain bit for
    bit, its Q gain and every output on every tick."""
    res = subprocess.run([str(exe), "--cov"], input=replay_cov_input(rec), capture_output=True,
                         text=True)
    assert res.returncode == 0 and not res.stderr, res.stderr[-2000:]
    outs, kq, rq, kf = parse_cov_output(res.stdout)
    assert len(outs) == len(rec)
    for k, (tin, out) in enumerate(rec):
        assert kf[k] == tin.k_f, f"tick {k}: C gain {kf[k]} != Python {tin.k_f}"
        assert kq[k] == tin.k_q and rq[k] == tin.r_q, f"tick {k}: the Q gain or bias differ"
        assert outs[k] == out, f"tick {k}: C {outs[k]} != Python {out}"


@pytest.mark.slow
def test_c_fixed_point_path_is_bit_exact_with_python_on_the_full_road_section(replay_exe):
    rec, rep = full_road_trace(PARITY_S)
    assert len(rec) == int(PARITY_S * 1000)
    assert rep["ecu_arithmetic"] == "fixed" and rep["fx_gain_saturations"] == 0
    # the trace covers every controller of the route and the crossfades between them
    wants = {i.want for i, _ in rec}
    assert wants >= {fp.CTRL_NONE, fp.CTRL_REGEN, fp.CTRL_BPPID, fp.CTRL_LQR,
                     fp.CTRL_GALQR}, wants
    # C: the one-call replay of each tick's hand-over gives the ECU's split path's integers
    res = subprocess.run([str(replay_exe)], input=trace_text(rec), capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert len(lines) == len(rec)
    for k, (text, (_, out)) in enumerate(zip(lines, rec)):
        assert tuple(int(v) for v in text.split()) == out, f"tick {k}: C {text} != Python {out}"
    duties = {out[0] for _, out in rec}
    assert len(duties) > 1000   # the duty moves: the comparison is not of constants
    # the whole estimator in C: R-hat adapts on the route, the guard and the gain move
    assert sum(1 for i, _ in rec if i.cov_flags & COV_ADAPT) > 0.9 * len(rec)
    assert len({i.k_f for i, _ in rec}) > 0.9 * len(rec)
    assert_estimator_bit_exact(replay_exe, rec)


def test_c_is_bit_exact_through_a_sensor_left_out(replay_exe):
    """A deflection sensor biased 3 mm from 2 s on: named, left out, the filter and the
    controllers restarted (the hand-over's reset) and driven on in comfort; C follows."""
    rec = sensor_fault_trace()
    resets = [k for k, (tin, _) in enumerate(rec) if tin.reset]
    assert len(resets) == 1 and 2000 < resets[0] < 3000, resets
    res = subprocess.run([str(replay_exe)], input=trace_text(rec), capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    for k, (text, (_, out)) in enumerate(zip(res.stdout.splitlines(), rec)):
        assert tuple(int(v) for v in text.split()) == out, f"tick {k}: C {text} != Python {out}"
    assert len({out[0] for _, out in rec[resets[0]:]}) > 100   # (driven on after it)
    # the estimator in C: the held measurement, the restart and the reduced filter after it
    assert rec[resets[0]][0].cov_flags & COV_RESTART
    assert any(i.cov_flags & 0b111 for i, _ in rec[resets[0] + 1:])
    assert_estimator_bit_exact(replay_exe, rec)


def test_c_is_bit_exact_through_a_sensor_left_out_between_ticks(replay_exe):
    """``Ecu.leave_out`` mid-drive (between two ticks, as tools.degraded and a workshop
    would): the restart is the next tick's, in its hand-over (the reset and COV_RESTART), so
    the C path and the C estimator restart where Python does."""
    rec = left_out_trace(at_tick=1500)
    resets = [k for k, (tin, _) in enumerate(rec) if tin.reset]
    assert resets == [1500], resets
    assert rec[1500][0].cov_flags & COV_RESTART
    res = subprocess.run([str(replay_exe)], input=trace_text(rec), capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    for k, (text, (_, out)) in enumerate(zip(res.stdout.splitlines(), rec)):
        assert tuple(int(v) for v in text.split()) == out, f"tick {k}: C {text} != Python {out}"
    assert len({out[0] for _, out in rec[1500:]}) > 100   # (driven on after it)
    assert_estimator_bit_exact(replay_exe, rec)


@pytest.mark.slow
def test_c_fixed_point_path_is_bit_exact_with_bump_stops_and_lift_off(tmp_path):
    """Off the linear model: the bump stops' force (a known input from the measured stroke,
    ``bump_force`` in firmware/fx/path.py and c/ecu_fx.c) on a vehicle that has them, driven
    hard enough to hit them, with the vehicle's own tables compiled in."""
    cfg, gen, rec = bump_stop_trace(tmp_path)
    exe = compile_c(tmp_path / "replay", replay_sources(gen), gen=gen)
    params = sil.ecu_params(cfg, "safety")
    assert params.akf.bump_stiffness > 0
    T = build_tables(params)
    over = [i for i, _ in rec if i.counts[2] is not None
            and abs(params.adc.susp_defl.range_min + i.counts[2] * params.adc.susp_defl.lsb)
            > params.akf.bump_clearance_m]
    assert len(over) > 50          # the drive does hit the bump stops
    res = subprocess.run([str(exe)], input=trace_text(rec), capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    for k, (text, (_, out)) in enumerate(zip(res.stdout.splitlines(), rec, strict=True)):
        assert tuple(int(v) for v in text.split()) == out, f"tick {k}: C {text} != Python {out}"
    assert T.bump_k.m != 0
    # off the model: the stroke and the current beyond their sensors add process noise
    assert any(i.cov_flags & (COV_LIFTED | COV_CURRENT_UNKNOWN | COV_STROKE_UNKNOWN)
               for i, _ in rec)
    assert_estimator_bit_exact(exe, rec)


SANITIZE = ("-fsanitize=undefined,address", "-fno-sanitize-recover=all", "-g")


@pytest.mark.slow
def test_c_path_is_clean_under_ubsan_and_asan(tmp_path):
    """The host build with UndefinedBehaviorSanitizer and AddressSanitizer (every report
    fatal: a shift out of range, a signed overflow, an out-of-bounds table read) replays the
    80 s of every controller and the crossfades, still bit-exact; the bench path and a
    malformed trace run clean too."""
    exe = compile_c(tmp_path / "replay_san", REPLAY_SOURCES, *SANITIZE)
    rec, _ = full_road_trace(PARITY_S)
    text = trace_text(rec)
    res = subprocess.run([str(exe)], input=text, capture_output=True, text=True)
    assert res.returncode == 0 and not res.stderr, res.stderr[-2000:]
    lines = res.stdout.splitlines()
    assert len(lines) == len(rec)
    for k, (line, (_, out)) in enumerate(zip(lines, rec)):
        assert tuple(int(v) for v in line.split()) == out, f"tick {k}: C {line} != Python {out}"
    res = subprocess.run([str(exe), "--bench", "2"], input=text, capture_output=True, text=True)
    assert res.returncode == 0 and not res.stderr, res.stderr[-2000:]
    assert_estimator_bit_exact(exe, rec)
    exe32 = compile_c(tmp_path / "replay_san32", REPLAY_SOURCES, *SANITIZE, "-DAKF_FLOAT")
    res = subprocess.run([str(exe32), "--cov"], input=replay_cov_input(rec),
                         capture_output=True, text=True)
    assert res.returncode == 0 and not res.stderr, res.stderr[-2000:]
    assert len(res.stdout.splitlines()) == len(rec)
    res = subprocess.run([str(exe)], input="1 2 3\n", capture_output=True, text=True)
    assert res.returncode == 2 and "malformed" in res.stderr and "Sanitizer" not in res.stderr


def test_c_replay_rejects_a_malformed_trace(replay_exe):
    res = subprocess.run([str(replay_exe)], input="1 2 3\n", capture_output=True, text=True)
    assert res.returncode == 2 and "malformed" in res.stderr
    for args, text in ((["--bench", "3"], "1 2 3\n"), (["--bench", "3"], ""),
                       (["--cov"], "1 2 3 4 0x1p-3 8 0\n"), (["--cov"], "1 2 3 4 x 8 0 0 0 0\n"),
                       (["--cov", "1"], ""),
                       (["--bench", "0"], "1\n"), (["--bench"], "1\n"), (["-x", "1"], "")):
        res = subprocess.run([str(replay_exe), *args], input=text, capture_output=True,
                             text=True)
        assert res.returncode == 2, (args, res.stderr)
        assert res.stderr.startswith(("trace_replay: ", "usage: ")), (args, res.stderr)


def test_c_replay_bench_times_the_same_ticks(replay_exe):
    """--bench (make bench's c_core_tick_us) runs the trace it read: its checksum folds every
    tick's duty and force, the same in every repetition."""
    rec = []
    sil.run(default_vehicle(), load_route("full_road_section"), "auto", 1, fixed_point=True,
            fx_record=rec, duration_s=2.0)
    text = trace_text(rec)
    checksum = 0
    for _, out in rec:
        checksum = (checksum * 31 + (out[0] & 0xFFFF) + (out[1] & 0xFFFFFFFF)) % 2 ** 64
    for repeats in (1, 3):
        res = subprocess.run([str(replay_exe), "--bench", str(repeats)], input=text,
                             capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        words = res.stdout.split()
        assert words[0::2] == ["ticks", "best_ns_per_tick", "median_ns_per_tick", "checksum"]
        assert int(words[1]) == len(rec) == 2000
        assert 0 < float(words[3]) <= float(words[5])
        want = checksum
        for _ in range(repeats - 1):      # (the checksum runs on across the repetitions)
            for _, out in rec:
                want = (want * 31 + (out[0] & 0xFFFF) + (out[1] & 0xFFFFFFFF)) % 2 ** 64
        assert int(words[7]) == want


# ---------------------------------------------------------------- cantools C


def test_cantools_generated_c_packs_like_the_python_encoder(tmp_path):
    dbc = ROOT / "dbc" / "suspension.dbc"
    subprocess.run([sys.executable, "-m", "cantools", "generate_c_source", str(dbc),
                    "-o", str(tmp_path)], check=True, capture_output=True)
    compile_c(tmp_path / "suspension.o", [tmp_path / "suspension.c"], "-c")
    from cantools.database.can.c_source import camel_to_snake_case

    codec = Codec()
    db = cantools.database.load_file(dbc)
    rng = random.Random(5)
    body, expected = [], []
    for m in db.messages:
        msg = camel_to_snake_case(m.name)
        for n in range(12):
            raw = {}
            for sig in m.signals:
                lo, hi = raw_range(sig)
                raw[sig.name] = (lo, hi, 0)[n] if n < 3 else rng.randint(lo, hi)
            data = codec.encode_raw(m.name, raw, counter=n % 16)
            full = m.decode(data, scaling=False, decode_choices=False)   # with COUNTER/CHECKSUM
            fields = " ".join(f"v.{camel_to_snake_case(k)} = {int(x)};" for k, x in full.items())
            body.append(f"  {{ struct suspension_{msg}_t v; uint8_t d[8] = {{0}}; int i, r;\n"
                        f"    memset(&v, 0, sizeof v); {fields}\n"
                        f"    r = suspension_{msg}_pack(d, &v, sizeof d);\n"
                        f"    if (r != {len(data)}) return 1;\n"
                        f'    for (i = 0; i < r; i++) {{ printf("%02x", d[i]); }}\n    printf("\\n"); }}')
            expected.append(data.hex())
    harness = tmp_path / "harness.c"
    harness.write_text('#include <stdio.h>\n#include <string.h>\n#include "suspension.h"\n'
                       "int main(void) {\n" + "\n".join(body) + "\n  return 0;\n}\n")
    exe = compile_c(tmp_path / "harness", [harness, tmp_path / "suspension.c"], f"-I{tmp_path}")
    res = subprocess.run([str(exe)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == expected
    assert len(expected) == 12 * len(db.messages)
