"""Vehicle TOML: the contract keys, defaults, and one clear error line for every bad input."""

import subprocess
import sys
from pathlib import Path

import pytest

from hil.config import DEFAULT_VEHICLE_FILE, ConfigError, default_vehicle, load_vehicle

ROOT = Path(__file__).resolve().parents[1]

GOOD = """\
[vehicle]
sprung_mass_kg = 320.0
unsprung_mass_kg = 40.0
spring_stiffness_n_per_m = 20000.0
damping_n_s_per_m = 1000.0
tire_stiffness_n_per_m = 200000.0
"""


def write(tmp_path: Path, text: str, name: str = "car.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_default_is_table3():
    v = default_vehicle().vehicle
    assert (v.sprung_mass_kg, v.unsprung_mass_kg, v.spring_stiffness_n_per_m,
            v.damping_n_s_per_m, v.tire_stiffness_n_per_m) == (320.0, 40.0, 20000.0, 1000.0, 200000.0)
    assert load_vehicle(None) is default_vehicle()
    assert load_vehicle(DEFAULT_VEHICLE_FILE).vehicle == v


def test_minimal_file_takes_defaults_for_other_tables(tmp_path):
    cfg = load_vehicle(write(tmp_path, GOOD.replace("320.0", "400.0")))
    assert cfg.vehicle.sprung_mass_kg == 400.0
    assert cfg.actuator == default_vehicle().actuator
    assert cfg.sensors == default_vehicle().sensors


def test_partial_override_of_other_tables(tmp_path):
    cfg = load_vehicle(write(tmp_path, GOOD + "[actuator]\ncurrent_limit_a = 25.0\n"
                                              "[sensors.body_accel]\nbits = 16\n"))
    assert cfg.actuator.current_limit_a == 25.0
    assert cfg.actuator.screw_lead_m == default_vehicle().actuator.screw_lead_m
    assert cfg.sensors.body_accel.bits == 16
    assert cfg.sensors.body_accel.noise_std == default_vehicle().sensors.body_accel.noise_std


def test_shipped_suv_loads():
    cfg = load_vehicle(ROOT / "hil" / "vehicles" / "suv.toml")
    assert cfg.vehicle.sprung_mass_kg == 520.0
    assert cfg.actuator.current_limit_a == 120.0


BAD_CASES = [
    # (description, file text, words the message must contain)
    ("missing key", GOOD.replace("damping_n_s_per_m = 1000.0\n", ""), ["vehicle.damping_n_s_per_m", "missing"]),
    ("unknown key", GOOD + "wheelbase_m = 2.7\n", ["vehicle.wheelbase_m", "unknown"]),
    ("unknown table", GOOD + "[engine]\npower = 1\n", ["engine", "unknown"]),
    ("zero", GOOD.replace("40.0", "0.0"), ["vehicle.unsprung_mass_kg", "positive"]),
    ("negative", GOOD.replace("1000.0", "-5.0"), ["vehicle.damping_n_s_per_m", "positive"]),
    ("nan", GOOD.replace("20000.0", "nan"), ["vehicle.spring_stiffness_n_per_m", "finite"]),
    ("inf", GOOD.replace("200000.0", "inf"), ["vehicle.tire_stiffness_n_per_m", "finite"]),
    ("string", GOOD.replace("320.0", '"heavy"'), ["vehicle.sprung_mass_kg", "number"]),
    ("bool", GOOD.replace("320.0", "true"), ["vehicle.sprung_mass_kg", "number"]),
    ("no vehicle table", "[actuator]\ncurrent_limit_a = 3.0\n", ["[vehicle]", "missing"]),
    ("broken toml", GOOD + "[actuator\n", ["invalid TOML"]),
    ("bad sub key", GOOD + "[actuator]\nlead = 1\n", ["actuator.lead", "unknown"]),
    ("efficiency > 1", GOOD + "[actuator]\nscrew_efficiency = 1.5\n", ["actuator.screw_efficiency"]),
    ("adc bits", GOOD + "[sensors.susp_defl]\nbits = 40\n", ["sensors.susp_defl.bits"]),
    ("adc range", GOOD + "[sensors.susp_defl]\nrange_min = 1.0\nrange_max = 0.5\n", ["sensors.susp_defl.range_max"]),
    ("unknown sensor", GOOD + "[sensors.lidar]\nbits = 12\n", ["sensors.lidar", "unknown"]),
    ("bool flag type", GOOD + "[nonlinear]\nbump_stops = 1\n", ["nonlinear.bump_stops"]),
]


@pytest.mark.parametrize("desc,text,words", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_vehicle_file_gives_one_clear_line(tmp_path, desc, text, words):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_vehicle(path)
    msg = str(exc.value)
    assert "\n" not in msg
    assert str(path) in msg
    for word in words:
        assert word in msg


def test_unreadable_and_non_utf8_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_vehicle(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="cannot read"):
        load_vehicle(tmp_path)  # a directory
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match="UTF-8"):
        load_vehicle(binary)


@pytest.mark.parametrize("argv", [
    ["-m", "tools.analysis", "thresholds"],
    ["-m", "tools.analysis", "passive", "--grade", "B", "--speed", "20"],
    ["-m", "tools.analysis", "limits", "--grade", "B", "--speed", "20"],
    ["-m", "hil", "drive", "--route", "city"],
])
def test_cli_bad_vehicle_exits_2_with_one_line(tmp_path, argv):
    path = write(tmp_path, GOOD.replace("40.0", "-1.0"))
    proc = subprocess.run([sys.executable, *argv, "--vehicle", str(path), "--json"],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "vehicle.unsprung_mass_kg" in lines[0] and str(path) in lines[0]


# -- design options (calib.options) -------------------------------------------------------------

def test_a_design_file_overrides_the_named_constants(tmp_path):
    from calib.ecu_params import build
    from calib.options import DesignOptions, load_options

    path = write(tmp_path, "[design]\nsafety_dtd_limit = 0.5\nadc_rail_ticks = 5\n"
                           "comprehensive_bound = [0.9, 0.95, 0.97]\nakf_adaptive = false\n")
    opts = load_options(path)
    assert opts.safety_dtd_limit == 0.5 and opts.adc_rail_ticks == 5 and not opts.akf_adaptive
    assert opts.comprehensive_bound == (0.9, 0.95, 0.97)
    assert opts.skyhook_c == DesignOptions().skyhook_c            # the rest: the defaults
    p, p0 = build(default_vehicle(), opts), build(default_vehicle())
    assert p.adc.rail_ticks == 5 and p0.adc.rail_ticks == 3
    ratio = p.modes.safety_dtd_rms_limit / p0.modes.safety_dtd_rms_limit
    assert ratio == pytest.approx(0.5 / 0.55, rel=1e-12)
    assert not p.akf.adaptive and p0.akf.adaptive


@pytest.mark.parametrize("text, words", [
    ("[design]\nno_such_option = 1\n", ["design.no_such_option", "unknown"]),
    ("[design]\nsafety_dtd_limit = -0.5\n", ["design.safety_dtd_limit", "positive"]),
    ("[design]\nsafety_dtd_limit = nan\n", ["design.safety_dtd_limit", "finite"]),
    ("[design]\nadc_rail_ticks = 2.5\n", ["design.adc_rail_ticks", "integer"]),
    ("[design]\nakf_adaptive = 1\n", ["design.akf_adaptive", "true or false"]),
    ("[design]\nbp_scale_ratio = [1, 2]\n", ["design.bp_scale_ratio", "3 positive numbers"]),
    ("[other]\nx = 1\n", ["other", "only [design]"]),
    ("[design\n", ["invalid TOML"]),
])
def test_a_bad_design_file_is_one_line_naming_the_key(tmp_path, text, words):
    from calib.options import load_options

    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_options(path)
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg
    for word in words:
        assert word in msg


def test_hil_sim_takes_a_design_file(tmp_path):
    """--design with the defaults written out gives the same trace as without; a bad file is
    one line and exit code 2."""
    from calib.options import DesignOptions

    defaults = DesignOptions()
    good = write(tmp_path, "[design]\nsafety_dtd_limit = %r\nramp_s = %r\n"
                 % (defaults.safety_dtd_limit, defaults.ramp_s))
    base = [sys.executable, "-m", "hil", "sim", "--route", "city", "--duration", "2", "--json"]
    runs = [subprocess.run(base + extra, capture_output=True, text=True, cwd=ROOT, timeout=300)
            for extra in ([], ["--design", str(good)])]
    assert all(r.returncode == 0 for r in runs), runs[1].stderr[-2000:]
    import json

    assert json.loads(runs[0].stdout)["trace_sha256"] == json.loads(runs[1].stdout)["trace_sha256"]
    bad = tmp_path / "bad.toml"
    bad.write_text("[design]\nramp_s = 0\n")
    proc = subprocess.run(base + ["--design", str(bad)], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "design.ramp_s" in proc.stderr


# ---------------------------------------------------------------- every key's physical range

def _keys():
    """Every numeric key of a vehicle file: (TOML table path, key, its field's metadata)."""
    import dataclasses

    from calib.vehicle import (SENSOR_KEYS, ActuatorParams, NonlinearParams, SensorChannel,
                               SimParams, VehicleParams)

    out = []
    for table, cls in (("vehicle", VehicleParams), ("actuator", ActuatorParams),
                       ("nonlinear", NonlinearParams), ("sim", SimParams)):
        out += [((table,), f.name, f.metadata) for f in dataclasses.fields(cls)
                if f.metadata.get("kind") != "bool"]
    for ch in SENSOR_KEYS:
        out += [(("sensors", ch), f.name, f.metadata) for f in dataclasses.fields(SensorChannel)]
    return out


ABSURD = (0, -1, 1e-30, 1e30, float("nan"), float("inf"), float("-inf"), 1)


@pytest.mark.parametrize("value", ABSURD, ids=[repr(v) for v in ABSURD])
def test_every_key_is_checked_against_its_physical_range(tmp_path, value):
    """Every number of a vehicle file with 0, negative, tiny, huge, NaN, ±inf (and 1): the
    file is refused in one ConfigError line naming the key, or the value lies inside the
    key's documented range (docs/plant.md) and the whole car passes its cross-checks."""
    import math
    import tomllib

    import tomli_w

    from calib.vehicle import CHANNEL_LIMITS

    base = tomllib.loads(DEFAULT_VEHICLE_FILE.read_text())
    docs = (Path(__file__).resolve().parents[1] / "docs" / "plant.md").read_text()
    for tables, key, meta in _keys():
        data = tomllib.loads(tomli_w.dumps(base))
        t = data
        for name in tables:
            t = t[name]
        t[key] = int(value) if meta.get("integer") and math.isfinite(value) else value
        path = write(tmp_path, tomli_w.dumps(data))
        full = ".".join((*tables, key))
        try:
            load_vehicle(path)
        except ConfigError as exc:
            text = str(exc)
            assert "\n" not in text and str(path) in text, text
            continue
        lo, hi = meta.get("range", (None, None))
        if key in ("range_min", "range_max"):
            lo, hi = -CHANNEL_LIMITS[tables[1]], CHANNEL_LIMITS[tables[1]]
        assert lo is not None and lo <= value <= hi, f"{full} = {value!r} accepted"
        if "range" in meta and not meta.get("integer") and math.isfinite(hi):
            assert f"| `{full}` | {lo:g} | {hi:g} |" in docs, f"{full}'s range is not in docs"
