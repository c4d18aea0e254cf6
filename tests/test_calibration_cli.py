"""``--calibration FILE``: any car driven with any car's calibration from the command line, on
the campaign's ``nominal`` path (``calib.vehicle.on_calibration``): the same bytes as a
campaign case, over SIL and the bench."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from calib.vehicle import on_calibration, static_sag_m
from hil.config import DEFAULT_VEHICLE_FILE, load_vehicle

ROOT = Path(__file__).resolve().parents[1]
SUV = ROOT / "hil" / "vehicles" / "suv.toml"
PAYLOAD = 1.15                             # +15 % sprung mass: a loaded default car


def _loaded(tmp_path: Path) -> Path:
    """The default car with its payload and its bump stops, written as a campaign writes the
    factor (the base value times it)."""
    text = DEFAULT_VEHICLE_FILE.read_text()
    mass = load_vehicle(None).vehicle.sprung_mass_kg
    assert "sprung_mass_kg = 320.0\n" in text and "bump_stops = false\n" in text
    text = text.replace("sprung_mass_kg = 320.0\n", f"sprung_mass_kg = {mass * PAYLOAD!r}\n")
    path = tmp_path / "loaded.toml"
    path.write_text(text.replace("bump_stops = false\n", "bump_stops = true\n"))
    return path


def _sim(*argv: str) -> tuple[subprocess.CompletedProcess, dict]:
    p = subprocess.run([sys.executable, "-m", "hil", "sim", "--json", *argv],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    return p, (json.loads(p.stdout) if p.stdout.strip() else {})


def test_the_driven_car_sits_at_its_calibrations_ride_height(tmp_path):
    car, cal = load_vehicle(_loaded(tmp_path)), load_vehicle(None)
    moved = on_calibration(car, cal)
    sag = static_sag_m(car.vehicle, cal.vehicle)
    assert sag < -0.02 and moved.nonlinear.static_deflection_m == sag   # 15 %: 23.5 mm down
    assert moved.vehicle == car.vehicle and moved.actuator == car.actuator
    assert on_calibration(cal, cal) is cal                             # nothing moves


def test_its_own_calibration_changes_no_byte():
    a, ra = _sim("--vehicle", str(SUV), "--route", "full_road_section", "--duration", "4")
    b, rb = _sim("--vehicle", str(SUV), "--calibration", str(SUV), "--route",
                 "full_road_section", "--duration", "4")
    assert a.returncode == b.returncode == 0, a.stderr + b.stderr
    assert ra["trace_sha256"] == rb["trace_sha256"]
    assert "calibration" not in ra and rb["calibration"] == str(SUV)


@pytest.mark.hil
@pytest.mark.xdist_group("hub_bench")       # (two benches at once overload 2 cores)
def test_sim_and_bench_drive_a_loaded_car_as_the_campaigns_nominal_case(tmp_path):
    """hil sim, hil run (lockstep) and a campaign case of the same car on its base car's
    calibration: one trace."""
    from hil.validate.campaign.case import run_case
    from hil.validate.campaign.spec import new_case

    loaded = _loaded(tmp_path)
    case = new_case({"name": "full_road_section"}, 1,
                    {"name": "default", "toml": None, "factors": {"sprung_mass_kg": PAYLOAD},
                     "nonlinear": {"bump_stops": True}, "sample": 1,
                     "calibration": "nominal"}, duration_s=3.0)
    row = run_case(case)
    assert row["trace_sha256"], row["failed"]
    p, rep = _sim("--vehicle", str(loaded), "--calibration", str(DEFAULT_VEHICLE_FILE),
                  "--route", "full_road_section", "--duration", "3")
    assert rep["trace_sha256"] == row["trace_sha256"], p.stderr
    # the ECU carries the default car's calibration, not the loaded car's own
    own = _sim("--vehicle", str(loaded), "--route", "full_road_section", "--duration", "3")[1]
    assert own["trace_sha256"] != rep["trace_sha256"]
    out = tmp_path / "run"
    run = subprocess.run([sys.executable, "-m", "hil", "run", "--json", "--out", str(out),
                          "--vehicle", str(loaded), "--calibration", str(DEFAULT_VEHICLE_FILE),
                          "--route", "full_road_section", "--duration", "3"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    bench = json.loads(run.stdout)
    assert bench["trace_sha256"] == rep["trace_sha256"], run.stderr[-2000:]
    assert bench["calibration"] == str(DEFAULT_VEHICLE_FILE)


@pytest.mark.parametrize("argv, want", [
    (["sim", "--calibration", "nowhere.toml"], "nowhere.toml"),
    (["sim", "--calibration", "{step}"], "plant step"),
    (["run", "--calibration", "{step}"], "plant step"),
    (["faults", "--calibration", str(SUV)], "sensor campaign's"),
])
def test_a_bad_calibration_is_one_line(tmp_path, argv, want):
    step = tmp_path / "step.toml"
    text = DEFAULT_VEHICLE_FILE.read_text()
    assert "plant_dt_s = 0.001\n" in text
    step.write_text(text.replace("plant_dt_s = 0.001\n", "plant_dt_s = 0.002\n"))
    argv = [a.replace("{step}", str(step)) for a in argv]
    p = subprocess.run([sys.executable, "-m", "hil", *argv, "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert want in p.stderr and "Traceback" not in p.stderr


def test_the_sensor_campaign_drives_each_car_on_the_calibration(tmp_path):
    from calib.dataset import image_sha256
    from hil.nodes import sil
    from hil.validate.sensorfaults import cars

    loaded = _loaded(tmp_path)
    car, params = cars(str(loaded), "table3.toml")
    assert car.nonlinear.static_deflection_m < -0.02
    assert image_sha256(params) == image_sha256(sil.ecu_params(load_vehicle(None), "comfort"))
    own, p_own = cars(str(loaded), None)
    assert own.nonlinear.static_deflection_m == 0.0
    assert image_sha256(p_own) != image_sha256(params)
