"""Bounded, clear input handling: every absurd input of issue 17 gets one error line and exit
2, before anything large is allocated; what cannot be scored is flagged, not scored."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from calib.control_design import default_gains_path
from hil.config import default_vehicle
from hil.transport.codec import Codec, DbcError

ROOT = Path(__file__).resolve().parents[1]
TABLE3 = (ROOT / "hil" / "vehicles" / "table3.toml").read_text()


def _route(tmp_path, body: str, road: str = "") -> str:
    path = tmp_path / "route.toml"
    path.write_text((f"[road]\n{road}\n" if road else "") + body)
    return str(path)


def _segment(length="100", speed="20", grade='grade = "B"') -> str:
    return f"[[segment]]\n{grade}\nlength_m = {length}\nspeed_mps = {speed}\n"


def _vehicle(tmp_path, key: str, value: str, *more: str) -> str:
    """TABLE3 with ``key = value`` (and ``more``'s pairs) written over its own."""
    lines = TABLE3.splitlines()
    pairs = (key, value, *more)
    for k, v in zip(pairs[::2], pairs[1::2]):
        lines = [f"{k} = {v}" if ln.split("=")[0].strip() == k else ln for ln in lines]
        assert any(ln == f"{k} = {v}" for ln in lines), k
    path = tmp_path / "vehicle.toml"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _one_line_error(args, want: str, timeout=120):
    proc = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-1500:])
    err = proc.stderr.strip()
    assert "Traceback" not in proc.stderr and err.count("\n") == 0, err
    assert want in err, err


@pytest.mark.parametrize("road,segment,want", [
    ("dx_m = 1e-7", _segment(), "'road.dx_m' must be in [0.001, 0.1] m"),
    ("cutoff_n_per_m = 1e-300", _segment(), "'road.cutoff_n_per_m' must be in [0.001"),
    ("", _segment(length="1e12"), "the route drives 5e+10 s; at most 1800 s"),
    ("", _segment(grade="gq_m3 = 5.0"), "'segment[0].gq_m3' must be in [1e-09, 0.1]"),
    ("dx_m = 0.001", _segment(length="30000"), "the road grid would hold 3e+07 points"),
    ("", _segment(length="700", speed="70"), "at most 69.94 m/s on this vehicle"),
])
def test_absurd_routes_are_one_line_errors(tmp_path, road, segment, want):
    _one_line_error(["-m", "hil", "sim", "--route", _route(tmp_path, segment, road),
                     "--duration", "1"], want)


@pytest.mark.parametrize("pairs,want", [
    (("sprung_mass_kg", "1e-6"), "'vehicle.sprung_mass_kg' must be in [20, 5000] (its "
                                 "physical range), got 1e-06"),
    (("unsprung_mass_kg", "2.0", "tire_stiffness_n_per_m", "1e7"),
     "fastest mode (356.2 Hz) is too fast for the plant step"),
    (("tire_stiffness_n_per_m", "1e4"), "vehicle.tire_stiffness_n_per_m sags 0.353 m"),
    (("current_limit_a", "1000.0", "torque_constant_nm_per_a", "0.2"),
     "exceeds 32767 N, FORCE_CMD's range"),
    (("winding_inductance_h", "1e30"), "'actuator.winding_inductance_h' must be in [1e-06, 1]"),
    (("bus_voltage_v", "1e30"), "'actuator.bus_voltage_v' must be in [1, 1000]"),
    (("bus_voltage_v", "2.0", "storage_voltage_v", "2.0"), "opposes the back-EMF (30 V s/m) only up to 0.0667 m/s"),
    (("noise_std", "1e30"), "'sensors.body_accel.noise_std' (1e+30) must be at most 0.1 of"),
])
def test_vehicles_that_cannot_be_simulated_are_refused_with_the_reason(tmp_path, pairs, want):
    key = pairs[0]
    path = _vehicle(tmp_path, *pairs)
    _one_line_error(["-m", "hil", "sim", "--vehicle", path, "--duration", "1"], want)
    if key == "winding_inductance_h":    # hil run: before any node starts (one line, exit 2)
        _one_line_error(["-m", "hil", "run", "--vehicle", path, "--out", str(tmp_path / "o"),
                         "--duration", "1"], want)
        assert not (tmp_path / "o").exists()
    if key == "sprung_mass_kg":          # the analysis tools too (they gave NaN, exit 0)
        for sub in ("passive", "limits"):
            _one_line_error(["-m", "tools.analysis", sub, "--grade", "B", "--speed", "20",
                             "--vehicle", path], want)


def test_gains_files_must_name_their_vehicle_and_stabilise_it(tmp_path):
    shipped = json.loads(default_gains_path(default_vehicle()).read_text())
    no_hash = dict(shipped)
    no_hash.pop("vehicle_sha256")
    flipped = dict(shipped, K=[-k for k in shipped["K"]])
    for name, doc, want in (("nohash", no_hash, "key 'vehicle_sha256' is missing"),
                            ("flipped", flipped, "make the closed loop unstable (pole at +")):
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(doc))
        _one_line_error(["-m", "hil", "sim", "--gains", str(path), "--duration", "1"], want)
        _one_line_error(["-m", "hil", "run", "--gains", str(path), "--out",
                         str(tmp_path / "o"), "--duration", "1"], want)


def test_out_problems_are_one_line(tmp_path):
    afile = tmp_path / "file"
    afile.write_text("x")
    _one_line_error(["-m", "hil", "sim", "--duration", "1", "--out", str(afile / "sub")],
                    "cannot create the directory")
    _one_line_error(["-m", "hil", "sim", "--duration", "1", "--out", str(afile)],
                    "cannot create the directory")


def test_dbc_problems_are_one_line(tmp_path):
    bad = tmp_path / "bad.dbc"
    bad.write_text('VERSION ""\nBO_ garbage\n')
    for path, want in ((tmp_path / "none.dbc", "cannot read the DBC: No such file"),
                       (bad, "not a valid DBC: ")):
        with pytest.raises(DbcError) as exc:
            Codec(path)
        assert want in str(exc.value) and "\n" not in str(exc.value)
    # and the command line turns one that escapes (a DBC is loaded at import) into one line
    code = ("import hil.transport.codec as c; from pathlib import Path; c.DBC_PATH = Path('/no/such.dbc');"
            " import hil.cli as cli; cli.run_main(lambda: c.Codec(c.DBC_PATH) and 0)")
    _one_line_error(["-c", code], "/no/such.dbc: cannot read the DBC")


def test_segments_shorter_than_the_settling_window_are_flagged_not_scored(tmp_path):
    route = _route(tmp_path, _segment(length="40") + _segment(length="200", grade='grade = "C"'))
    proc = subprocess.run([sys.executable, "-m", "hil", "sim", "--route", route, "--mode",
                           "comfort", "--json"], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-1500:]
    short, long_ = json.loads(proc.stdout)["segments"]
    assert short["scored"] is False and "not scored" in short["note"]
    assert short["ratio"] == {"ba": None, "sws": None, "dtd": None}
    assert long_["scored"] is True and 0 < long_["ratio"]["ba"] < 2


def test_a_grade_beyond_the_estimates_cap_is_not_scored_for_accuracy(tmp_path):
    """The grade estimate names A-D; on F it reads D, its cap, which is no right answer: the
    F segment's grade accuracy is not scored (NaN, null in the JSON) and the drive's is the B
    segment's alone (it was 1.0 on F, D counted as right)."""
    from hil.nodes.sil import run
    from hil.sim.road import load_route

    route = load_route(_route(tmp_path, _segment(length="400") +
                              _segment(length="200", speed="10", grade='grade = "F"')))
    rep, trace = run(default_vehicle(), route, "comfort", 1)
    b, f = rep["segments"]
    assert f["scored"] and math.isnan(f["grade_accuracy"]) and 0.0 < b["grade_accuracy"] <= 1.0
    assert rep["grade_accuracy"] == b["grade_accuracy"]
    late = trace.segment == 1
    assert (trace.true_grade[late] == 3).all()              # (SIM_TRUTH: capped at D)


def test_a_full_disk_under_out_is_one_line_and_leaves_no_temporary_file(tmp_path, monkeypatch,
                                                                        capsys):
    """``hil sim --out`` where the disk fills up: one line naming --out, exit 1, never a
    traceback from the log writer; and an atomic write that fails leaves no ``*.tmp``."""
    import errno

    from hil.__main__ import main
    from hil.cli import write_atomic
    from hil.transport.buslog import BusLogFile

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(BusLogFile, "write", full)
    with pytest.raises(SystemExit) as exc:
        main(["sim", "--route", "city", "--duration", "1", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 1 and "Traceback" not in err and len(err.splitlines()) == 1
    assert err.endswith(f"--out {tmp_path / 'run'}: cannot write: No space left on device")
    monkeypatch.setattr(Path, "replace", full)     # (written, then the rename fails)
    with pytest.raises(OSError):
        write_atomic(tmp_path / "report.json", "{}")
    assert list(tmp_path.glob("*.tmp")) == [] and not (tmp_path / "report.json").exists()


@pytest.mark.parametrize("argv,want", [
    (["diag"], "no bench to talk to"),                   # (was an AttributeError traceback)
    (["diag", "-c", "ws://127.0.0.1:9/"], "no bench to talk to"),
    (["xcp", "info"], "required: --key-file"),
    (["campaign"], "required: FILE.toml"),
    (["campaign-case"], "required: DB, CASE_ID"),
    ([], "required: command"),
    (["sim", "--mode"], "argument --mode: expected one argument"),
    (["logdiff", "a.log"], "required: LOG"),
    (["ecu", "--key-file", "{key}"], "ecu: no CAN bus: this kernel has no vcan0"),  # (was 3)
    (["plant", "-i", "pcan", "--key-file", "{key}"], "'pcan' needs a channel"),
    # the hub's secret is hil run's, not hil keygen's (it said: make one with hil keygen)
    (["diag", "-i", "remote", "-c", "ws://127.0.0.1:9/", "--secret-file", "nowhere.secret"],
     "no such key file (the hub's secret: hil run writes it as OUT/hub.secret"),
])
def test_documented_commands_with_missing_arguments_say_so_in_one_line(tmp_path, argv, want,
                                                                      monkeypatch):
    from hil.transport import secoc
    from hil.transport.bus import kernel_has_vcan

    if argv[:1] == ["ecu"] and kernel_has_vcan("vcan0"):
        pytest.skip("this kernel has vcan0: the node would open it and wait")
    monkeypatch.delenv("CAN_INTERFACE", raising=False)
    monkeypatch.delenv("CAN_CHANNEL", raising=False)
    key = tmp_path / "k"
    secoc.write_key(key)
    _one_line_error(["-m", "hil", *[a.replace("{key}", str(key)) for a in argv]], want)


def test_a_reused_sim_out_keeps_no_earlier_log_copy(tmp_path):
    """hil sim --out DIR again: the bus log copies of the earlier run (bus.asc here) go; the
    ones this run asks for are written anew (hil run's outputs are cleared the same way)."""
    out = tmp_path / "o"
    for fmt in ("asc", "trc"):
        p = subprocess.run([sys.executable, "-m", "hil", "sim", "--route", "city", "--duration",
                            "1", "--out", str(out), "--log-format", fmt, "--json"],
                           capture_output=True, text=True, cwd=ROOT, timeout=300)
        assert p.returncode == 0, p.stderr[-1500:]
    assert (out / "bus.trc").is_file() and not (out / "bus.asc").exists()
