"""Adaptive Kalman filter: filterpy parity, adaptation under a noise step, the R-hat guard,
and what the wheel accelerometer buys."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from calib.ecu_params import build
from calib.options import DesignOptions
from firmware import akf
from firmware.ecu import init as ecu_init
from firmware.kernels import akf as kern
from firmware.layout import params_record
from hil.config import default_vehicle
from hil.nodes import sil
from hil.sim.road import constant_route

CFG = default_vehicle()


class Filter:
    """The filter's compiled predict and update (``firmware.kernels.akf``) on its own arrays,
    filterpy's split, for the tests that drive it with made-up measurements."""

    def __init__(self, p):
        self.p, self.W = p, kern.workspace(p.H.shape[0])
        self.x, self.P, self.R = np.zeros(5), p.p0.copy(), p.r0.copy()
        self.r, self.b_pow, self.guard_hits = np.zeros(p.H.shape[0]), p.forgetting, 0
        self.r_scale = np.outer(np.sqrt(p.r_floor), np.sqrt(p.r_floor))

    def predict(self, u, road_intensity):
        p = self.p
        kern.predict_ws(p.phi, p.gamma, p.q_unit, self.x, self.P, float(u),
                        float(road_intensity), True, self.W)

    def update(self, z, u):
        p = self.p
        self.b_pow, hit = kern.update_ws(p.H, p.D, self.P, self.R, self.r, self.x,
                                         np.asarray(z, dtype=float), float(u), p.r_floor,
                                         self.r_scale, self.b_pow, p.forgetting, p.adaptive,
                                         p.bias_adaptive, self.W)
        self.guard_hits += int(hit)


def guard_r(R, floor):
    out = np.empty_like(R)
    hit = kern.guard(R, floor, np.outer(np.sqrt(floor), np.sqrt(floor)), out)
    return out, hit


def model_noise(p, speed):
    Q = p.road_intensity_per_mps * speed * p.q_unit
    w, V = np.linalg.eigh(Q)
    return V * np.sqrt(np.maximum(w, 0.0)), np.linalg.cholesky(p.r0)


def test_matches_filterpy_without_adaptation_over_10000_steps():
    p = build(CFG, DesignOptions(akf_adaptive=False)).akf
    rng = np.random.default_rng(0)
    speed = 20.0
    Lq, Lr = model_noise(p, speed)
    kf = KalmanFilter(dim_x=5, dim_z=3, dim_u=1)
    kf.F, kf.B, kf.H = p.phi.copy(), p.gamma.reshape(5, 1), p.H.copy()
    kf.R, kf.Q, kf.P = p.r0.copy(), p.road_intensity_per_mps * speed * p.q_unit, p.p0.copy()
    kf.x = np.zeros((5, 1))
    st = Filter(p)
    x = np.zeros(5)
    worst = 0.0
    for _ in range(10_000):
        u = rng.normal(0.0, 200.0)
        x = p.phi @ x + p.gamma * u + Lq @ rng.standard_normal(5)
        z = p.H @ x + p.D * u + Lr @ rng.standard_normal(3)
        st.predict(u, p.road_intensity_per_mps * speed)
        st.update(z, u)
        kf.predict(u=np.array([[u]]))
        kf.update((z - p.D * u).reshape(3, 1))   # filterpy has no feedthrough term
        scale = np.abs(kf.x).max()
        worst = max(worst, np.abs(st.x - kf.x.ravel()).max() / scale,
                    np.abs(st.P - kf.P).max() / np.abs(kf.P).max())
    assert worst < 1e-9


def road_error_after_noise_step(adaptive: bool, grade: str, speed: float) -> float:
    p = build(CFG, DesignOptions(akf_adaptive=adaptive))
    _, tr = sil.run(CFG, constant_route(grade, speed, 30.0), "passive", 4, params=p,
                    noise_step=(10.0, 4.0))
    a = tr.arrays
    lo = 12_000   # 2 s after the step
    z, e = a["zf"][:-1][lo:], a["road_est"][1:][lo:]
    return float(np.sqrt(np.mean((e - z) ** 2)))


@pytest.mark.slow
def test_adaptive_filter_beats_fixed_r_after_a_noise_step():
    """All sensors' noise steps up x4 at 10 s. A road at 10 m/s, where sensor noise matters
    against the road excitation (on rough roads the road dominates the innovations and the
    two filters are within a few per cent; see the README)."""
    adaptive = road_error_after_noise_step(True, "A", 10.0)
    fixed = road_error_after_noise_step(False, "A", 10.0)
    assert adaptive < fixed, (adaptive, fixed)


def test_r_guard_holds_on_adversarial_innovations():
    p = build(CFG).akf
    st = Filter(p)
    rng = np.random.default_rng(1)
    floor = p.r_floor
    for k in range(3000):
        st.predict(0.0, p.road_intensity_per_mps * 20.0)
        pred = p.H @ st.x
        kind = k % 4
        if kind == 0:
            z = pred.copy()                                   # zero innovation: R-hat falls
        elif kind == 1:
            z = pred + rng.normal(0, 1e3, 3)                  # huge innovation
        elif kind == 2:
            z = pred + np.array([1e-3, -1e-6, 1e-2]) * (-1) ** k  # correlated, alternating
        else:
            z = pred - 1e-12
        st.update(z, 0.0)
        R = st.R
        assert np.allclose(R, R.T)
        s = np.sqrt(floor)
        w = np.linalg.eigvalsh(R / np.outer(s, s))
        assert w.min() >= 1.0 - 1e-6 and w.max() <= kern.R_CEILING * (1 + 1e-6)
        assert np.all(np.isfinite(st.x)) and np.linalg.eigvalsh(st.P).min() > -1e-12
    assert st.guard_hits > 0
    # non-finite input: the guard falls back to the floor instead of propagating NaN
    R, hit = guard_r(np.full((3, 3), np.nan), floor)
    assert hit and np.all(np.isfinite(R))


@pytest.mark.slow
def test_wheel_accelerometer_makes_tyre_deflection_observable():
    """Measured: the tyre-deflection estimate with and without the wheel accelerometer."""
    errs = {}
    for use in (True, False):
        p = build(CFG, DesignOptions(use_wheel_accel=use))
        _, tr = sil.run(CFG, constant_route("C", 20.0, 15.0), "passive", 4, params=p)
        d, de = tr.arrays["dtd"][:-1][3000:], tr.arrays["dtd_est"][1:][3000:]
        errs[use] = float(np.sqrt(np.mean((de - d) ** 2)))
    assert errs[True] < 0.1 * errs[False], errs


def _with_nonlinear(cfg):
    import dataclasses

    return dataclasses.replace(cfg, nonlinear=dataclasses.replace(
        cfg.nonlinear, bump_stops=True, tire_lift_off=True), source="nonlinear")


def test_off_the_linear_model_bump_stops_lift_off_and_unmeasured_inputs():
    """docs/ecu.md, "The estimator off the linear model": the bump stops are a known force of
    the measured stroke (the same in both arithmetic paths), an airborne tyre and an input
    beyond its sensor add process noise along their force's input, and R-hat holds on such a
    tick."""
    from calib.fx_tables import build_tables
    from firmware.fixedpoint import to_fixed
    from firmware.fx.path import bump_force as fx_bump_force
    from firmware.fx.tables import F_FORCE, F_POS

    P = build(_with_nonlinear(CFG))
    a, ms, mt = P.akf, P.plant.ms, P.plant.mt
    A = params_record(P)[0]["akf"]
    c, k = a.bump_clearance_m, a.bump_stiffness
    assert (c, k) == (CFG.nonlinear.bump_stop_clearance_m, CFG.nonlinear.bump_stop_stiffness_n_per_m)
    assert akf.bump_force(A, 0.9 * c) == 0.0 and akf.bump_force(A, -0.9 * c) == 0.0
    assert akf.bump_force(A, c + 0.01) == pytest.approx(-k * 0.01)      # pushes the body down
    assert akf.bump_force(A, -c - 0.01) == pytest.approx(k * 0.01)
    T = params_record(build_tables(P))[0]
    for d in (0.0, c + 0.003, -c - 0.017, 0.0999):
        f = fx_bump_force(T, to_fixed(d, F_POS)) * 2.0 ** -F_FORCE
        assert f == pytest.approx(akf.bump_force(A, d), abs=0.01)
    lin_rec = params_record(build(CFG))[0]["akf"]
    assert akf.bump_force(lin_rec, 0.2) == 0.0                   # no bump stops, no force
    # the tyre force the accelerometers measure: the load standing, none in free fall
    g = a.tyre_load_n / (ms + mt)
    assert not akf.airborne(A, ms, mt, 0.0, 0.0) and akf.airborne(A, ms, mt, -g, -g)
    # process noise along the unknown force's input: the wheel's, or the actuator's
    st = ecu_init(P)[0]["akf"]
    p0 = st["P"].copy()
    akf.unknown_forces(A, st, True, False, False)
    assert np.allclose(st["P"] - p0, a.lift_force_sigma_n ** 2 * np.outer(a.gamma_wheel, a.gamma_wheel))
    st["P"] = p0
    akf.unknown_forces(A, st, False, True, True)
    assert np.allclose(st["P"] - p0, (a.current_force_sigma_n ** 2 + a.stroke_force_sigma_n ** 2)
                       * np.outer(a.gamma, a.gamma))
    lin = build(CFG)                                             # a tyre that cannot lift off
    assert lin.akf.lift_force_sigma_n == 0.0 and lin.akf.stroke_force_sigma_n == 0.0
    st = ecu_init(lin)[0]["akf"]
    p0 = st["P"].copy()
    akf.unknown_forces(lin_rec, st, True, False, True)
    assert np.array_equal(st["P"], p0)
    # R-hat holds on a tick whose inputs are not measurements, adapts otherwise
    for adapt in (False, True):
        st = ecu_init(P)[0]["akf"]
        r0 = st["R"].copy()
        akf.tick(A, st, 0.0, a.road_intensity_per_mps * 20.0, 5.0, 0.01, -40.0, 0.0, adapt, 0)
        assert np.array_equal(st["R"], r0) != adapt
