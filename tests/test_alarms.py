"""False alarms of the model-based fault detection, measured (issue 19): the make-test subset
of ``python -m hil alarms`` (the full set is a long command: docs/diagnostics.md), and that
the command fails when the tests do raise alarms."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from calib import cache
from hil.sim.road import load_route
from hil.validate import alarms

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_fault_free_drives_raise_no_alarm(tmp_path):
    """The city route at 10 and 30 m/s, both cars with bump stops and lift-off, 40 s each."""
    proc = subprocess.run([sys.executable, "-m", "hil", "alarms", "--routes", "city",
                           "--speeds", "10,30", "--seeds", "1", "--duration", "40", "--json",
                           "--out", str(tmp_path)], capture_output=True, text=True, cwd=ROOT,
                          timeout=900)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    doc = json.loads(proc.stdout)
    assert doc["verdict"] == "pass" and doc["cases"] == 4
    assert doc["detections"] == 0 and doc["dtcs_failed"] == []
    length = load_route("city").length_m
    assert sorted(r["driven_s"] for r in doc["results"]) == pytest.approx(
        sorted(min(40.0, length / v) for v in (10.0, 30.0) for _ in range(2)), abs=0.01)
    assert doc["hours_driven"] == pytest.approx(sum(r["driven_s"] for r in doc["results"]) / 3600)
    assert json.loads((tmp_path / "alarms.json").read_text())["cases"] == 4
    assert "alarms: 4/4" in proc.stderr                     # progress, one line per drive


@pytest.mark.slow
def test_a_rough_fast_drive_past_the_bump_stops_raises_no_alarm():
    """The worst drive of the full set before the estimator took the bump stops, an airborne
    tyre and sensors past their range into account (46 detections at 8ab7f13):
    the default car on `country` at 30 m/s, its D stretch hitting the bump stops, lifting the
    tyre and taking the current and the stroke past their sensors' ranges."""
    doc = alarms.summarise(alarms.measure(alarms.cases(["country"], ["table3.toml"], [30.0],
                                                       [9]), jobs=1))
    r = doc["results"][0]
    assert r["driven_s"] == pytest.approx(load_route("country").length_m / 30.0, abs=0.01)
    assert doc["detections"] == 0 and doc["dtcs_failed"] == [] and doc["verdict"] == "pass", r


def test_the_command_fails_when_the_tests_alarm(monkeypatch):
    """Sabotage: a false-alarm probability of 0.5 per window puts the innovation tests' level
    near the noise itself; the measurement must see it and the verdict fail."""
    import dataclasses

    from calib.options import DesignOptions

    from hil.nodes import sil

    def sabotaged(**changes):        # (the design a run takes by default)
        return dataclasses.replace(DesignOptions(), fdi_false_alarm=0.5, **changes)

    monkeypatch.setattr(sil, "DesignOptions", sabotaged)
    monkeypatch.setenv(cache.ENV_OFF, "1")     # (nothing of it kept on disk)
    doc = alarms.summarise(alarms.measure(alarms.cases(["city"], ["table3.toml"], [20.0], [1],
                                                       duration_s=5.0), jobs=1))
    assert doc["detections"] > 0 and doc["verdict"] == "fail"
    assert doc["worst"][0]["command"].startswith("python -m hil alarms --routes city")


def test_bad_arguments_are_one_line():
    for args, want in ((["--seeds", "x"], "seeds"), (["--speeds", "0"], "speeds"),
                       (["--routes", "nope"], "nope")):
        p = subprocess.run([sys.executable, "-m", "hil", "alarms", *args], capture_output=True,
                           text=True, cwd=ROOT, timeout=120)
        assert p.returncode == 2 and want in p.stderr and "Traceback" not in p.stderr
