"""Tuning over XCP against the exact analysis: a gain row written during a run changes the
ride as the analysis of the new gain predicts; the working page saved as a design file runs
the same; the checks a write and a design file's [calibration] table pass (calib.calpage)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calib import calpage
from calib.errors import ConfigError
from calib.fx_tables import build_tables, pinned
from calib.iso8608 import GRADE_GQ_M3
from calib.model import linear_model, window_covariance
from calib.options import DesignOptions, load_options
from hil.config import default_vehicle
from hil.nodes import EcuNode, PlantNode, run_in_process
from hil.nodes.sil import app_node, ecu_params
from hil.sim.road import constant_route
from tests.test_xcp import CODEC, KEY, _write_between_ticks

CFG = default_vehicle()
GRADE, SPEED, SECONDS = "C", 20.0, 60.0
W, SETTLE = 5000, 1000                   # the write's tick; ticks to settle before measuring


def log_ratios(t: dict, start: int) -> np.ndarray:
    """log RMS ratios to the passive twin [BA, SWS, DTD] of plant trace ``t`` from tick
    ``start`` on."""
    s = slice(start, None)
    return np.array([np.log(np.sqrt(np.mean(t[k][s] ** 2) / np.mean(t["p_" + k][s] ** 2)))
                     for k in ("ba", "sws", "dtd")])


def predicted_change(k0, k1, grade: str, speed: float, window_s: float):
    """(predicted, sigma): the change in log ratios that the exact analysis gives for gain
    ``k1`` against ``k0`` on a car already under ``k0``, and the scatter of that paired
    difference over a window of ``window_s`` (``window_covariance`` of the car under K0 as
    the baseline, K1 - K0 as the change)."""
    k0, k1 = np.asarray(k0), np.asarray(k1)
    m = linear_model(CFG.vehicle, GRADE_GQ_M3[grade], speed)
    under_k0 = dataclasses.replace(m, A=m.A - np.outer(m.B, k0), C=m.C - np.outer(m.D, k0))
    ratio, cov = window_covariance(under_k0, k1 - k0, window_s)
    return np.log(ratio), np.sqrt(np.diag(cov))


def drive(route, opts=None, writes=None, key: bytes = KEY, ticks=None):
    """A lockstep drive of ``route`` in safety mode, seed 1, in this process: (plant trace,
    ECU trace). ``writes``: (tick, name, values), written over XCP between that tick and the
    one before; ``ticks``: the drive's first ticks only (as ``hil run --duration``)."""
    p = ecu_params(CFG, "safety", opts=opts)
    plant = PlantNode(CFG, route, 1, CODEC, key=key)
    if ticks is not None:
        plant.n = min(plant.n, ticks)
    ecu = EcuNode(p, CODEC, lockstep=True, key=key)
    app = app_node(CODEC, "safety", p.dt_s, key=key)
    if writes:
        tick, name, values = writes
        run_in_process(plant, ecu, app, until=tick)
        _write_between_ticks(ecu, name, values)
    run_in_process(plant, ecu, app)
    assert not ecu.trace()["faults"].any()          # (no fault on the way)
    return plant.trace(), ecu.trace()


def _drive(opts=None, writes=None) -> np.ndarray:
    """log ratios over ticks [W + SETTLE, end) of a drive at GRADE, SPEED for SECONDS."""
    route = constant_route(GRADE, SPEED, SECONDS)
    t, _ = drive(route, opts, writes and (W, *writes))
    return log_ratios(t, W + SETTLE)


def test_a_gain_row_written_during_a_run_changes_the_ride_as_the_analysis_predicts():
    """The safety LQR's row halved over XCP at tick W: the change in log ratios over the rest
    of the drive (against the same drive unchanged, same seed: the same road) is what the exact
    analysis of the new gain predicts for a car already under the old one, within 3 sigma of
    that paired difference's scatter; the change itself is many sigma (the check can fail).
    The same gain from the start, as a design file's [calibration] sets it, gives the same
    segment to rounding of the settled transient."""
    p = ecu_params(CFG, "safety")
    k0 = np.asarray(p.control.k_safety)
    k1 = 0.5 * k0
    r0 = _drive()
    r1 = _drive(writes=("cal.control.k_safety", k1))
    rc = _drive(opts=DesignOptions(calibration=(("control.k_safety", tuple(k1)),)))
    predicted, sigma = predicted_change(k0, k1, GRADE, SPEED, SECONDS - (W + SETTLE) * p.dt_s)
    measured = r1 - r0
    assert np.all(np.abs(measured - predicted) < 3 * sigma), (measured, predicted, sigma)
    assert np.max(np.abs(measured) / sigma) > 10, (measured, sigma)
    assert np.max(np.abs(rc - r1)) < 1e-3, (rc, r1)


def test_a_design_calibration_table_is_checked_and_read_back(tmp_path):
    p = ecu_params(CFG, "auto")
    k = np.asarray(p.control.k_safety)
    f = tmp_path / "tuned.toml"
    f.write_text(calpage.design_text({"control.k_safety": (k * 0.75).tolist(),
                                      "modes.safety_hold_ticks": 4000}, header="a test"))
    o = load_options(f)
    q = ecu_params(CFG, "auto", opts=o)
    np.testing.assert_array_equal(q.control.k_safety, k * 0.75)     # bit for bit
    assert q.modes.safety_hold_ticks == 4000 and isinstance(q.modes.safety_hold_ticks, int)
    assert f.read_text().startswith("# a test\n")
    bad = {"unknown": ({"control.nope": 1.0}, "not a writable calibration object"),
           "size": ({"control.k_safety": [1.0, 2.0]}, "2 values, the object has 5"),
           "limits": ({"control.k_safety": (k * 5).tolist()}, "outside"),
           "unstable": ({"control.k_safety": (k * 1.5).tolist()}, "unstable"),
           "whole": ({"modes.safety_hold_ticks": 4000.5}, "whole number"),
           "nan": ({"control.k_safety": [float("nan")] * 5}, "finite")}
    for what, (table, text) in bad.items():
        g = tmp_path / f"{what}.toml"
        g.write_text(calpage.design_text(table))
        with pytest.raises(ConfigError, match=text):
            ecu_params(CFG, "auto", opts=load_options(g))
    g = tmp_path / "nested.toml"
    g.write_text("[design]\ncalibration = 1\n")
    with pytest.raises(ConfigError, match="unknown key 'design.calibration'"):
        load_options(g)


def test_a_written_calibration_keeps_the_fixed_point_formats_of_the_a2l():
    """The tables of a write are in the formats the ECU was built with (the A2L's COMPU
    METHODs): a smaller gain keeps its Q-format, one that no longer fits it is refused."""
    p = ecu_params(CFG, "auto")
    ref = build_tables(p)
    k = np.asarray(p.control.k_safety)
    smaller = build_tables(calpage.replace_path(p, ("control", "k_safety"), k * 0.5))
    assert [f.frac for f in smaller.k_safety] != [f.frac for f in ref.k_safety]
    t = pinned(smaller, ref)
    assert [f.frac for f in t.k_safety] == [f.frac for f in ref.k_safety]
    np.testing.assert_allclose([f.m * 2.0 ** -f.frac for f in t.k_safety], k * 0.5, rtol=1e-6)
    larger = build_tables(calpage.replace_path(p, ("control", "k_safety"), k * 2.0))
    with pytest.raises(ValueError, match="does not fit its fixed-point format"):
        pinned(larger, ref)


def test_every_writable_object_as_built_passes_the_checks_of_a_write():
    """The limits follow from the design's value, so the reference page itself passes them
    (for each car shipped): a write of one element is never refused for the others."""
    from pathlib import Path

    from hil.config import load_vehicle

    suv = Path(__file__).resolve().parents[1] / "hil" / "vehicles" / "suv.toml"
    for cfg in (CFG, load_vehicle(suv)):
        p = ecu_params(cfg, "auto")
        refused = {n: calpage.refusal(p, n, calpage.value_of(p, tuple(n.split("."))))
                   for n in calpage.WRITABLE}
        assert not any(refused.values()), {n: w for n, w in refused.items() if w}
