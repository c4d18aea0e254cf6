"""Sensor noise and ADC quantisation; RMS, W_k weighting, events."""

import math

import numpy as np
import pytest
from scipy.signal import freqz

from calib.vehicle import SensorChannel

from firmware.fixedpoint import round_half_away
from hil.config import default_vehicle
from hil.sim.metrics import peak, rising_edges, rms, wk_digital, wk_weighted_rms
from hil.sim.sensors import SensorSuite, from_counts, to_counts

CH = SensorChannel(noise_std=0.0, range_min=-10.0, range_max=10.0, bits=12)


def test_round_half_away_from_zero():
    assert [round_half_away(x) for x in (0.5, 1.5, 2.5, -0.5, -1.5, 0.49, -0.49)] == [1, 2, 3, -1, -2, 0, 0]


def test_adc_quantisation_and_saturation():
    assert to_counts(CH, -10.0) == 0 and to_counts(CH, 10.0) == 4095
    assert to_counts(CH, -99.0) == 0 and to_counts(CH, 99.0) == 4095      # saturate, never wrap
    assert to_counts(CH, math.inf) == 4095 and to_counts(CH, -math.inf) == 0
    assert to_counts(CH, math.nan) == 0
    for v in np.linspace(-9.99, 9.99, 101):
        assert abs(from_counts(CH, to_counts(CH, v)) - v) <= CH.lsb / 2 + 1e-12
    assert to_counts(CH, -10.0 + 2.51 * CH.lsb) == 3 and to_counts(CH, -10.0 + 2.49 * CH.lsb) == 2


def test_sensor_noise_is_seeded_and_has_configured_std():
    params = default_vehicle().sensors
    a = SensorSuite(params, np.random.default_rng(5))
    b = SensorSuite(params, np.random.default_rng(5))
    c = SensorSuite(params, np.random.default_rng(6))
    ra = [a.sample(0.0, 0.0, 0.0, 0.0, 20.0) for _ in range(2000)]
    rb = [b.sample(0.0, 0.0, 0.0, 0.0, 20.0) for _ in range(2000)]
    rc = [c.sample(0.0, 0.0, 0.0, 0.0, 20.0) for _ in range(2000)]
    assert ra == rb and ra != rc
    body = np.array([from_counts(params.body_accel, r.body_accel) for r in ra])
    expected = math.sqrt(params.body_accel.noise_std ** 2 + params.body_accel.lsb ** 2 / 12)
    assert body.std() == pytest.approx(expected, rel=0.1)


def test_rms_peak_events():
    t = np.arange(0, 10, 0.001)
    assert rms(3 * np.sin(2 * np.pi * t)) == pytest.approx(3 / math.sqrt(2), rel=1e-4)
    assert peak(np.array([1.0, -4.0, 2.0])) == 4.0
    assert rising_edges(np.array([1, 1, 0, 1, 0, 0, 1, 1], dtype=bool)) == 3
    assert rising_edges(np.zeros(0, dtype=bool)) == 0


# ISO 2631-1 Table 3, W_k (factor x 1000) at some one-third-octave centres
WK_TABLE = {0.5: 418, 1.0: 482, 2.0: 531, 4.0: 967, 8.0: 1036, 16.0: 768, 31.5: 405}


@pytest.mark.parametrize("f_hz,factor", WK_TABLE.items())
def test_wk_weighting_matches_iso_table(f_hz, factor):
    b, a = wk_digital(1000.0)
    _, h = freqz(b, a, [f_hz], fs=1000.0)
    assert abs(h[0]) == pytest.approx(factor / 1000, rel=0.02)


def test_wk_weighted_rms_of_a_sine():
    t = np.arange(0, 20, 0.001)
    x = np.sin(2 * np.pi * 4.0 * t)
    assert wk_weighted_rms(x, 1000.0) == pytest.approx(0.967 / math.sqrt(2), rel=0.02)
