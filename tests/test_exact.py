"""Design-time numerics that give the same bits on every host (calib.exact, calib.grid,
calib.dataset): each agrees with scipy's to its conditioning, and the committed calibration
reads back to the bytes it was written from."""

import dataclasses
import json

import numpy as np
import pytest
from scipy.linalg import expm, solve_discrete_are, solve_discrete_lyapunov

from calib import dataset, exact, grid
from calib.ecu_params import build
from calib.model import filter_discrete
from calib.options import DesignOptions
from hil.config import default_vehicle, load_vehicle
from tools.calibration import moved

CFG = default_vehicle()
RNG = np.random.default_rng(7)


def test_expm_agrees_with_scipy_on_the_models():
    A, *_ = filter_discrete(CFG, 1e-3)
    for M in (A * 1e-3, A * 0.05, RNG.normal(size=(7, 7))):
        want = expm(M)
        assert np.max(np.abs(exact.expm(M) - want)) <= 1e-13 * np.max(np.abs(want))


def test_stein_and_riccati_solve_what_scipy_solves():
    A = RNG.normal(size=(5, 5))
    A *= 0.95 / np.max(np.abs(np.linalg.eigvals(A)))
    Q = RNG.normal(size=(5, 5))
    Q = Q @ Q.T
    X = exact.solve_stein(A, Q)
    assert np.allclose(X, solve_discrete_lyapunov(A, Q), rtol=1e-10, atol=1e-12)
    assert np.max(np.abs(A @ X @ A.T + Q - X)) <= 1e-13 * np.max(np.abs(X))
    H = RNG.normal(size=(2, 5))
    R = np.diag([0.3, 0.7])
    P, K = exact.dare_filter(A, H, Q, R)
    Ps = solve_discrete_are(A.T, H.T, Q, R)
    assert np.allclose(P, Ps, rtol=1e-9, atol=1e-12)
    assert np.allclose(K, Ps @ H.T @ np.linalg.inv(H @ Ps @ H.T + R), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="not stable"):
        exact.solve_stein(A / 0.5, Q)


def test_the_grid_rounds_to_32_bits_and_flushes_noise_to_plus_zero():
    x = np.array([1.0 + 2.0 ** -40, -3.0, 1e-20, -1e-20, 0.1])
    g = grid.snap(x)
    assert g[0] == 1.0 and g[1] == -3.0 and g[2] == 0.0 and g[3] == 0.0
    assert not np.signbit(g[3])                       # +0, whatever the sign was
    assert abs(g[4] - 0.1) <= 2.0 ** -33 * 0.1 and g[4] != 0.1
    assert np.array_equal(grid.snap(g), g)            # idempotent
    assert grid.snap(5) == 5 and grid.snap(np.inf) == np.inf
    assert isinstance(grid.snap(0.1), float)


def test_the_committed_calibration_reads_back_to_its_bytes():
    for name in ("table3.toml", "suv.toml"):
        doc = json.loads(dataset.path_for(name).read_text())
        p = dataset.decode(doc["params"])
        assert dataset.image_sha256(p) == doc["image_sha256"]
        again = dataset.decode(json.loads(json.dumps(dataset.encode(p))))
        assert dataset.image_sha256(again) == doc["image_sha256"]
        assert bytes(again.calibration_sha256).hex() == doc["calibration_sha256"]
    # what runs load is the committed data: the default car and the SUV from their files
    assert dataset.image_sha256(build(CFG)) == json.loads(
        dataset.path_for("table3.toml").read_text())["image_sha256"]
    suv = load_vehicle("hil/vehicles/suv.toml")
    assert dataset.image_sha256(build(suv)) == json.loads(
        dataset.path_for("suv.toml").read_text())["image_sha256"]


def test_another_car_or_option_is_designed_not_served_the_shipped_data():
    shipped = build(CFG)
    heavier = dataclasses.replace(CFG, vehicle=dataclasses.replace(
        CFG.vehicle, sprung_mass_kg=CFG.vehicle.sprung_mass_kg * 1.01))
    assert build(heavier).plant.ms == pytest.approx(CFG.vehicle.sprung_mass_kg * 1.01)
    other = build(CFG, DesignOptions(safety_bound=0.97))
    assert not np.array_equal(other.control.k_safety, shipped.control.k_safety)


def test_a_damaged_data_file_is_refused_with_its_reason(tmp_path):
    doc = json.loads(dataset.path_for("table3.toml").read_text())
    doc["params"]["control"]["k_safety"]["data"][0] += 1.0
    bad = tmp_path / "table3.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="damaged or hand-edited"):
        dataset._read(bad)


def test_the_check_names_each_value_that_moved():
    p = build(CFG)
    k = p.control.k_safety.copy()
    k[2] *= 1.0 + 1e-6
    q = dataclasses.replace(p, control=dataclasses.replace(p.control, k_safety=k))
    rows = moved(p, q)
    assert [(m["path"], m["index"]) for m in rows] == [("control.k_safety", 2)]
    assert rows[0]["change"] == pytest.approx(abs(k[2] * 1e-6 / (1 + 1e-6))
                                              / np.max(np.abs(p.control.k_safety)), rel=1e-3)
    assert moved(p, p) == []
