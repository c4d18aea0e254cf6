"""The fixed-point control path: its arithmetic (round half away from zero, saturation), its
building blocks against the float ones, and its control quality against the float ECU on the
firmware acceptance scenarios (RMS BA, SWS, DTD within 1 %)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from calib.fx_tables import build_tables
from firmware import safety
from firmware.fixedpoint import (INT32_MAX, INT32_MIN, add, best_frac, div_round, mul, neg,
                                 round_half_away, rshift_round, sat16, to_fixed, to_float)
from firmware.fx.path import adc_signal, tanh_q
from firmware.fx.tables import ADC_FRAC, F_NN
from firmware.layout import params_record
from hil.config import default_vehicle
from hil.nodes import sil
from hil.sim.road import constant_route

CFG = default_vehicle()
INT32 = st.integers(INT32_MIN, INT32_MAX)


def test_rounding_is_half_away_from_zero():
    assert [rshift_round(p, 1) for p in (3, 1, -1, -3, 2, -2)] == [2, 1, -1, -2, 1, -1]
    assert rshift_round(5, 2) == 1 and rshift_round(6, 2) == 2 and rshift_round(-6, 2) == -2
    assert to_fixed(0.5, 0) == 1 and to_fixed(-0.5, 0) == -1 and to_fixed(-1.5, 0) == -2
    assert div_round(5, 2) == 3 and div_round(-5, 2) == -3 and div_round(4, 3) == 1


def test_saturation_never_wraps():
    assert add(INT32_MAX, 1) == INT32_MAX and add(INT32_MIN, -1) == INT32_MIN
    assert neg(INT32_MIN) == INT32_MAX
    assert mul(INT32_MAX, INT32_MAX, 0) == INT32_MAX and mul(INT32_MIN, INT32_MAX, 0) == INT32_MIN
    assert sat16(40000) == 32767 and sat16(-40000) == -32768
    assert to_fixed(1e30, 10) == INT32_MAX and to_fixed(-1e30, 10) == INT32_MIN


@settings(max_examples=300, deadline=None, derandomize=True)
@given(INT32, INT32, st.integers(0, 62))
def test_mul_is_the_exactly_rounded_saturated_product(a, b, s):
    exact = a * b / 2 ** s
    r = mul(a, b, s)
    assert INT32_MIN <= r <= INT32_MAX
    if INT32_MIN <= round(exact) <= INT32_MAX and abs(a * b) < 2 ** 52:
        assert abs(r - exact) <= 0.5
        assert r == round_half_away(exact)


def test_best_frac_keeps_the_most_bits_that_fit():
    for v in (0.001, 0.67, 1.0, 3.3, 682.7, 38815.5):
        f = best_frac(v)
        assert abs(to_fixed(v, f)) <= INT32_MAX < abs(round(v * 2.0 ** (f + 1)))
    with pytest.raises(ValueError):
        best_frac(float("nan"))


def test_tanh_table_is_accurate_and_odd():
    T = params_record(build_tables(sil.ecu_params(CFG, "auto")))[0]
    xs = np.linspace(-9.0, 9.0, 4001)
    err = max(abs(to_float(tanh_q(T, to_fixed(x, F_NN)), F_NN) - math.tanh(x))
              for x in xs)
    assert err < 1e-5
    for x in (0.3, 2.0, 7.99):
        q = to_fixed(x, F_NN)
        assert tanh_q(T, -q) == -tanh_q(T, q)


def test_adc_scaling_matches_the_float_conversion():
    p = sil.ecu_params(CFG, "auto")
    T = params_record(build_tables(p))[0]
    chans = (p.adc.body_accel, p.adc.wheel_accel, p.adc.susp_defl, p.adc.motor_current)
    for k, ch in enumerate(chans):
        for counts in (0, 1, 1234, 2048, ch.full_scale):
            q = adc_signal(T, k, counts)
            lsb_out = 2.0 ** -ADC_FRAC[k]
            assert abs(to_float(q, ADC_FRAC[k]) - (ch.range_min + counts * ch.lsb)) <= lsb_out
    assert adc_signal(T, 0, -1) == 0               # (no good sample yet)


# ---------------------------------------------------------------- control quality

SCENARIOS = [("comfort", "B", 120.0), ("safety", "C", 60.0), ("comprehensive", "D", 60.0),
             ("regen", "A", 60.0)]


@pytest.mark.slow
@pytest.mark.parametrize("mode,grade,seconds", SCENARIOS)
def test_fixed_point_control_is_within_one_percent_of_float(mode, grade, seconds):
    route = constant_route(grade, 20.0, seconds)
    flt, _ = sil.run(CFG, route, mode, 1)
    fxp, _ = sil.run(CFG, route, mode, 1, fixed_point=True)
    assert flt["ecu_arithmetic"] == "float" and fxp["ecu_arithmetic"] == "fixed"
    assert fxp["fx_gain_saturations"] == 0
    a, b = flt["segments"][0], fxp["segments"][0]
    for key in ("ba_rms_mps2", "sws_rms_m", "dtd_rms_m"):
        assert abs(b["active"][key] / a["active"][key] - 1.0) <= 0.01, (key, a["active"], b["active"])
    # the two paths are not the same computation (else this test could not fail)
    assert flt["trace_sha256"] != fxp["trace_sha256"]
    if mode == "regen":
        assert abs(b["harvested_w"] / a["harvested_w"] - 1.0) <= 0.01


def test_a_diverged_covariance_is_a_fault_not_a_crash_in_the_fixed_path():
    from firmware.ecu import Ecu, Inputs

    p = sil.ecu_params(CFG, "comfort")
    e = Ecu(p, build_tables(p), record=True)
    inp = Inputs(tick=0, body_accel=2048, wheel_accel=2048, susp_defl=2048,
                 motor_current=2048, speed=2000)
    out = e.step(inp)
    e.akf.P[0, 0] = float("nan")
    out = e.step(inp._replace(tick=1))
    assert out.faults & safety.FAULT_NONFINITE_ESTIMATE and not out.enable
    assert list(e.S[0]["fx"]["x"]) == [0] * 5 and e.log[-1][0].reset
    out = e.step(inp._replace(tick=2))
    assert not out.faults & safety.FAULT_NONFINITE_ESTIMATE
