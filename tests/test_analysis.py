"""Lyapunov analysis, thresholds and the exact physical limits (tools.analysis)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.config import default_vehicle, load_vehicle
from calib.model import linear_model, output_covariance, passive_rms
from hil.road import gq_of
from tools.analysis import limits, passive, thresholds
from calib.linear import Normalised, physical_limits

ROOT = Path(__file__).resolve().parents[1]
CFG = default_vehicle()
SUV = load_vehicle(ROOT / "hil" / "vehicles" / "suv.toml")


def test_passive_cross_check_with_errata_reference_analysis():
    """The errata's independent Lyapunov analysis (literal convention, B road, 20 m/s):
    BA 0.920 m/s², SWS 9.51 mm, DTD 3.25 mm. Agreement checks the corrected model (errata 1-3);
    the paper's A-matrix typo gives DTD 18 mm instead."""
    ba, sws, dtd = passive_rms(linear_model(CFG.vehicle, gq_of("B"), 20.0, "paper"))
    assert ba == pytest.approx(0.920, abs=0.0005)
    assert sws == pytest.approx(9.51e-3, abs=0.005e-3)
    assert dtd == pytest.approx(3.25e-3, abs=0.005e-3)


def test_iso_is_paper_over_sqrt2_and_grades_scale_by_2():
    iso = passive_rms(linear_model(CFG.vehicle, gq_of("C"), 17.0, "iso"))
    paper = passive_rms(linear_model(CFG.vehicle, gq_of("C"), 17.0, "paper"))
    np.testing.assert_allclose(paper / iso, np.sqrt(2), rtol=1e-9)
    d = passive_rms(linear_model(CFG.vehicle, gq_of("D"), 17.0, "iso"))
    np.testing.assert_allclose(d / iso, 2.0, rtol=1e-9)


def test_thresholds_separate_grades_over_10_to_30_mps():
    """Section 4.3: indicators grow with speed, and C at 10 m/s exceeds B at 30 m/s, so the
    thresholds from B@30 (DTD), B@10 (BA) and C@30 (BA) separate the grades."""
    th = thresholds(CFG)
    for v in (10.0, 15.0, 20.0, 25.0, 30.0):
        b = passive_rms(linear_model(CFG.vehicle, gq_of("B"), v))
        c = passive_rms(linear_model(CFG.vehicle, gq_of("C"), v))
        assert b[2] <= th["dtd1_m"] * (1 + 1e-12)
        assert c[2] > th["dtd1_m"]
        assert b[0] >= th["ba1_mps2"] * (1 - 1e-12)
        assert c[0] <= th["ba2_mps2"] * (1 + 1e-12)
    assert th["ba1_mps2"] < th["ba2_mps2"]
    paper = thresholds(CFG, "paper")
    assert paper["dtd1_m"] == pytest.approx(np.sqrt(2) * th["dtd1_m"], rel=1e-9)


def check_limits(cfg, grade, speed):
    model = linear_model(cfg.vehicle, gq_of(grade), speed)
    res = physical_limits(model)
    p_var, _ = output_covariance(model)
    # recompute each optimum from its physical gain, independently of the optimiser
    for name, r in res.items():
        var, _ = output_covariance(model, r.K)
        np.testing.assert_allclose(np.sqrt(var / p_var), r.ratios, rtol=1e-5, err_msg=name)
    c, s, b = res["comfort"].ratios, res["safety"].ratios, res["balanced"].ratios
    assert c[1] <= 1 + 1e-6 and c[2] <= 1 + 1e-6 and res["comfort"].value == pytest.approx(c[0], rel=1e-6)
    assert s[0] <= 1 + 1e-6 and s[1] <= 1 + 1e-6 and res["safety"].value == pytest.approx(s[2], rel=1e-6)
    assert np.max(b) == pytest.approx(res["balanced"].value, rel=1e-5)
    e = res["eq43"].ratios
    assert np.all(e <= 1 + 1e-6) and res["eq43"].value == pytest.approx(e.sum(), rel=1e-6)
    # no sampled LQR weighting beats the limits (the limits are a lower bound on what any
    # weighting can do; random search would find a violation of a wrong limit)
    norm = Normalised.of(model)
    rng = np.random.default_rng(0)
    for _ in range(300):
        w = 10.0 ** rng.uniform(-3, 4, 3)
        _, var = norm.lqr(w)
        r = np.sqrt(var)
        if r[1] <= 1 and r[2] <= 1:
            assert r[0] >= res["comfort"].value - 1e-6
        if r[0] <= 1 and r[1] <= 1:
            assert r[2] >= res["safety"].value - 1e-6
        assert r.max() >= res["balanced"].value - 1e-6
        if np.all(r <= 1):
            assert r.sum() >= res["eq43"].value - 1e-6
    return res


def test_limits_default_car_and_errata_frontier():
    res = check_limits(CFG, "B", 20.0)
    # every limit is a real improvement over passive (passive is feasible)
    assert res["comfort"].value < 1 and res["safety"].value < 1 and res["balanced"].value < 1
    assert res["eq43"].value < 3
    # cross-check with the errata's independent frontier: 0.788, 0.844, about -9.7 %
    assert res["comfort"].value == pytest.approx(0.788, abs=0.001)
    assert res["safety"].value == pytest.approx(0.844, abs=0.001)
    assert res["balanced"].value == pytest.approx(0.903, abs=0.002)


def test_limits_other_vehicle_and_speed():
    check_limits(SUV, "D", 12.0)


def test_limits_are_grade_independent():
    b = physical_limits(linear_model(CFG.vehicle, gq_of("B"), 20.0))
    d = physical_limits(linear_model(CFG.vehicle, gq_of("D"), 20.0))
    for k in b:
        assert b[k].value == pytest.approx(d[k].value, rel=1e-5)


def run_cli(*args):
    proc = subprocess.run([sys.executable, "-m", "tools.analysis", *args, "--json"],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_cli_json_contracts():
    p = run_cli("passive", "--grade", "B", "--speed", "20", "--simulate", "30", "--seed", "2")
    assert {"ba_rms_mps2", "sws_rms_m", "dtd_rms_m"} <= p.keys()
    assert {"ba_rms_mps2", "sws_rms_m", "dtd_rms_m"} <= p["simulation"].keys()
    assert p["ba_rms_mps2"] == pytest.approx(passive(CFG, "B", 20.0)["ba_rms_mps2"], rel=1e-12)
    t = run_cli("thresholds", "--convention", "paper")
    assert {"dtd1_m", "ba1_mps2", "ba2_mps2"} <= t.keys()
    lim = run_cli("limits", "--grade", "C", "--speed", "20", "--vehicle", str(ROOT / "hil/vehicles/suv.toml"))
    assert {"comfort_ba_ratio", "safety_dtd_ratio", "balanced_ratio", "eq43_fitness"} <= lim.keys()
    assert lim["comfort_ba_ratio"] == pytest.approx(limits(SUV, "C", 20.0)["comfort_ba_ratio"], rel=1e-6)


def test_cli_rejects_bad_arguments():
    proc = subprocess.run([sys.executable, "-m", "tools.analysis", "passive", "--grade", "Z",
                           "--speed", "20"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode == 2 and "grade" in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "tools.analysis", "passive", "--grade", "B",
                           "--speed", "-3"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode == 2 and "speed" in proc.stderr.lower()


@pytest.mark.parametrize("vehicle", ["default", "suv"])
def test_the_comfort_design_follows_the_vehicle(vehicle):
    """calib.ecu_params.comfort_total_gain for each car: exact SWS and DTD ratios within
    the design's bounds, the static stiffness rule, BA near that car's own limit, and a loop
    stable over the BP-PID's whole K_i range (build raises otherwise)."""
    from calib.ecu_params import build, comfort_total_gain
    from calib.options import DesignOptions

    cfg = default_vehicle() if vehicle == "default" else SUV
    opts = DesignOptions()
    model = linear_model(cfg.vehicle, gq_of("C"), 20.0)
    res = comfort_total_gain(cfg, opts, model)
    ks = cfg.vehicle.spring_stiffness_n_per_m
    assert res.ratios[1] <= opts.comfort_bound[0] and res.ratios[2] <= 1.0
    assert ks + res.K[2] >= opts.comfort_min_stiffness * ks
    gap = res.value - limits(cfg, "C", 20.0)["comfort_ba_ratio"]
    assert 0.0 < gap < 0.035, gap
    p = build(cfg, opts)
    assert p.control.k_comfort[0] == pytest.approx(res.K[0] - p.control.bp_scale[1])
    assert p.control.bp_scale[1] > 0.5 * res.K[0]      # the network carries the skyhook


def test_a_process_designs_each_vehicle_once_and_nobody_changes_the_design():
    """calib.ecu_params keeps the feedback designs per process: a second build of the same
    vehicle and options gives equal gains without designing again, the kept arrays are
    read-only, and other options design anew."""
    import dataclasses

    from calib import ecu_params
    from calib.options import DesignOptions

    ecu_params._feedback_designs.cache_clear()
    first = ecu_params.build(SUV, DesignOptions())
    again = ecu_params.build(SUV, DesignOptions())
    assert ecu_params._feedback_designs.cache_info().hits == 1
    for a, b in ((first.control.k_comfort, again.control.k_comfort),
                 (first.control.k_safety, again.control.k_safety)):
        assert np.array_equal(a, b)
        with pytest.raises(ValueError):
            a[0] = 0.0
    other = ecu_params.build(SUV, dataclasses.replace(DesignOptions(), safety_bound=0.9))
    assert not np.array_equal(other.control.k_safety, first.control.k_safety)
