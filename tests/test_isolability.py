"""The isolability analysis (issue 40, tools.isolability over calib.fdi_bank): its exact
propagation of the innovations' mean and covariance checked against a Monte Carlo run of the
filter itself, the bank's blindness, and the one physical equivalence the analysis rests on
(a constant force error is invisible to the accelerometers)."""

import math
import dataclasses

import numpy as np
import pytest
from scipy.linalg import expm

from calib import fdi_bank as fb
from calib.model import filter_continuous
from calib.options import DesignOptions
from hil.config import default_vehicle
from calib import isolability as iso
from tools import isolability as iso_tool

CFG = default_vehicle()
OPTS = DesignOptions()


@pytest.fixture(scope="module")
def banks():
    return {s: fb.generators(CFG, dataclasses.replace(OPTS, fdi_bank_structure=s))
            for s in ("voltage", "force")}


def _passive_case():
    A5, B5 = filter_continuous(CFG)
    q = fb.road_intensity(CFG, OPTS, "B", 20.0)
    return A5, B5, iso.Case("passive", A5, np.zeros(5), q, 0.0)


def test_each_filter_is_blind_to_its_sensor_alone(banks):
    for bank in banks.values():
        for name, gen in bank.items():
            for sensor in fb.SENSORS:
                b, d = gen.fault_input(sensor)
                seen = bool(np.any(b) or np.any(d))
                assert seen == (sensor != name), (name, sensor)


@pytest.mark.parametrize("structure", ["voltage", "force"])
def test_healthy_statistic_is_one(banks, structure):
    """Without a fault the joint system's innovation covariance is the filter's own S (the
    propagation asserts it) and E[nu' S^-1 nu] / m stays 1."""
    A5, B5, case = _passive_case()
    A7 = fb.winding_continuous(CFG, A5, B5)
    sig = iso._signals(CFG, A5, B5, case.K)
    for name, gen in banks[structure].items():
        sensor = "ba" if name != "ba" else "defl"
        st = iso.propagate(gen, A7 if gen.phi.shape[0] == 7 else A5, case, sig, sensor, "bias",
                           0.0, 200, OPTS.dt_s, 1.0)
        assert np.allclose(st, 1.0, atol=1e-6), name


@pytest.mark.parametrize("kind,size", [("bias", 0.1), ("gain", 0.3)])
def test_propagation_matches_monte_carlo(banks, kind, size):
    """The filter blind to WA (force structure: BA, SWS; passive, so no force) run on 4000
    simulated drives of its own model with a BA fault from tick 0: the mean of nu' S^-1 nu / m
    per tick against the analysis's exact value."""
    gen = banks["force"]["wa"]
    A5, B5, case = _passive_case()
    sig = iso._signals(CFG, A5, B5, case.K)
    ticks, runs = 150, 4000
    exact = iso.propagate(gen, A5, case, sig, "ba", kind, size, ticks, OPTS.dt_s, 1.0)[:, 0]
    rng = np.random.default_rng(7)
    phi = expm(A5 * OPTS.dt_s)
    Q = case.intensity * gen.q_unit
    n, m = 5, gen.H.shape[0]
    # the stationary start of the car and of the filter's error
    from scipy.linalg import solve_discrete_lyapunov
    X = solve_discrete_lyapunov(phi, Q)
    x = rng.multivariate_normal(np.zeros(n), X, runs)
    a_e = gen.error_phi
    pk = gen.phi @ gen.K
    E = solve_discrete_lyapunov(a_e, Q + pk @ gen.r0 @ pk.T)
    xh = x - rng.multivariate_normal(np.zeros(n), E, runs)       # the prediction x-hat-
    S_inv = np.linalg.inv(gen.innovation_cov(case.intensity))
    w, V = np.linalg.eigh(Q)                       # (rank-deficient: one road input)
    chol_q, chol_r = V * np.sqrt(np.clip(w, 0.0, None)), np.linalg.cholesky(gen.r0)
    c_ba = sig["ba"]
    mc = np.empty(ticks)
    for t in range(ticks):
        z = x @ gen.H.T + rng.standard_normal((runs, m)) @ chol_r.T
        if kind == "bias":
            z[:, 0] += size
        else:
            z[:, 0] += size * (x @ c_ba)
        nu = z - xh @ gen.H.T
        mc[t] = np.mean(np.einsum("ri,ij,rj->r", nu, S_inv, nu)) / m
        xh = (xh + nu @ gen.K.T) @ phi.T
        x = x @ phi.T + rng.standard_normal((runs, n)) @ chol_q.T
    # each tick's mean of a chi2-like variable over 4000 runs: sd about sqrt(2 / m / runs)
    # times the statistic; averaged over blocks of 10 ticks the error is within 5 %
    blocks_mc = mc.reshape(-1, 10).mean(axis=1)
    blocks_ex = exact.reshape(-1, 10).mean(axis=1)
    assert np.all(np.abs(blocks_mc / blocks_ex - 1.0) < 0.05), (blocks_mc, blocks_ex)
    assert exact.max() > 1.5           # the fault shows: the comparison is not of two ones


def test_constant_force_error_is_invisible_to_the_accelerometers(banks):
    """A current bias is a constant force error: the filter reading only BA and WA (force
    structure) settles to a zero innovation (the car's static position shifts, which no
    accelerometer sees), while the one reading SWS does not. This is why slow current
    faults and a deflection sensor's slow faults are told apart by no filter."""
    for name, reads_sws in (("defl", False), ("wa", True)):
        gen = banks["force"][name]
        b, d = gen.fault_input("current")
        e = np.linalg.solve(np.eye(5) - gen.error_phi, b)
        nu = gen.H @ e + d
        S = gen.innovation_cov(fb.road_intensity(CFG, OPTS, "B", 20.0))
        z = np.abs(nu) / np.sqrt(np.diag(S))        # per ampere, in innovation sigmas
        assert (z.max() > 1.0) == reads_sws, (name, z)
        if not reads_sws:
            assert z.max() < 1e-6, z


def test_bank_options_refuse_bad_values():
    for bad in (dict(fdi_bank_structure="other"), dict(fdi_bank_offset_walk_v=0.0),
                dict(fdi_bank_window=0)):
        with pytest.raises(ValueError):
            fb.check_options(dataclasses.replace(OPTS, **bad))


def test_cli_refuses_bad_input(capsys):
    assert iso_tool.main(["--grade", "Z"]) == 2
    assert iso_tool.main(["--speed", "-3"]) == 2
    assert iso_tool.main(["--walk", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("isolability:") == 3


def test_clipped_square_matches_monte_carlo():
    """The ECU tests' clipped square, E[min(Z^2, c^2)], against 400,000 draws per case (a
    healthy innovation, one near the clip, one far above it); without a clip, var + mu^2."""
    rng = np.random.default_rng(3)
    for mu, var in ((0.0, 1.0), (4.0, 2.0), (40.0, 1.0)):
        z = mu + math.sqrt(var) * rng.standard_normal(400_000)
        mc = float(np.mean(np.minimum(z * z, 25.0)))
        assert abs(iso.clipped_square(mu, var, 25.0) / mc - 1.0) < 0.01, (mu, var, mc)
    assert iso.clipped_square(3.0, 2.0, math.inf) == 11.0
