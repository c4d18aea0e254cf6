"""Which single sensor faults the isolation bank can tell apart, and how fast: the analysis
of docs/diagnostics.md ("Isolability"), computed from the model (its CLI: ``tools.isolability``;
the sensor campaign ``hil faults --sensors`` drives the same faults and judges against it).

For each sensor (BA, WA, deflection, current), each fault (bias, drift, gain, stuck, noise x5,
an intermittent dropout) and two magnitudes (small 3 sigma, large 10 sigma of the sensor's own
noise; a drift reaches them in 10 s; a gain moves the signal's RMS by them), in comfort mode and
in the fail-safe (passive: the bridge open, the bank's open-bridge filters), it propagates the
exact mean and covariance of every filter's innovation (``calib.fdi_bank``) from the fault's
onset: the car, the filter's error and the fault as one linear system, the car in its
stationary state at the onset. The expected statistic of each test (the EWMA of the
normalised squared innovations, W ticks) then gives the time it crosses its level at the
designed false-alarm rate: the mean detection time of the ECU's tests and the time each bank
filter turns inconsistent. A fault is isolable where every filter that reads the sensor turns
inconsistent and the one blind to it cannot (its response is zero: checked; a failed
self-check raises AssertionError).

The expectation is of the statistic, not of its crossing time: a statistic whose mean just
reaches the level crosses it late or early by chance, so a test is taken to cross where its
expected statistic passes the level by ``RELIABLE_SD`` standard deviations of the test's
healthy scatter (what it does reliably, not on half the drives). Each tick's square is
clipped at ``fdi_clip_sigmas``^2 in the ECU's tests as in the firmware (exact for a Gaussian
innovation); the bank's clip is ignored: it matters only for faults far above the level (a
dropout's isolation time is early by it). The ECU tests' allowance for the measured force
(its efficiency band and its change over a tick, ``firmware.diag.fdi``) is modelled as the
band alone: their times for faults of the force's path (the current) are early.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib import fdi_bank as fb
from calib.options import NOMINAL_SPEED_MPS, DesignOptions

KINDS = ("bias", "drift", "gain", "stuck", "noise", "dropout")
MAGNITUDES = {"small": 3.0, "large": 10.0}    # in the sensor's noise sigma
DRIFT_S = 10.0                                 # a drift reaches its magnitude in this time
NOISE_FACTOR = 5.0                             # the noise fault: sigma x this
DROPOUT_ON, DROPOUT_PERIOD = 5, 100            # ticks read as 0 (mid-scale) in every period
HORIZON_S = {"drift": 12.0}                    # how long each fault is followed (else 10 s)
HORIZON_DEFAULT_S = 10.0
# a test counts as crossing where its expected statistic passes its level by this many
# standard deviations of its healthy scatter (``scatter``): a mean that just reaches the
# level crosses only half the time (the wheel accelerometer's 10-sigma gain on the default
# car ends 0.04 above the bank's level in the fail-safe: named in none of three drives)
RELIABLE_SD = 2.0
CONDITIONS = ("comfort", "passive")
SIGNAL_ROWS = {"ba": 0, "wa": 1}               # rows of A for the accelerations


@dataclass
class Case:
    """The car in one condition: its closed loop and the noise its filters see."""
    name: str
    A_cl: np.ndarray     # (5, 5) the car under its law, continuous
    K: np.ndarray        # (5,) the law u = -K x
    intensity: float     # road intensity
    var_force: float     # the force error's variance (the screw efficiency's band)
    X: np.ndarray | None = None   # (5, 5) the car's stationary covariance


def _signals(cfg, A5, B5, K):
    """The true channels as rows over the car's state: {sensor: c} with y = c x."""
    kf = cfg.actuator.force_constant_n_per_a
    u = -np.asarray(K, dtype=float)
    return {"ba": A5[0] + B5[0] * u, "wa": A5[1] + B5[1] * u,
            "defl": np.array([0, 0, 1.0, -1.0, 0]), "current": u / kf}


def _joint_noise(A_cl: np.ndarray, A_f: np.ndarray, n_f: int, dt: float, intensity: float):
    """The discrete covariance of the road noise integrated over one tick through the car
    (closed loop) and through the filter's model (open loop) together: (5 + n_f) square."""
    from calib.model import van_loan_integral
    n = 5 + n_f
    A = np.zeros((n, n))
    A[:5, :5] = A_cl
    A[5:, 5:] = A_f
    g = np.zeros(n)
    g[4] = g[5 + 4] = 1.0
    return van_loan_integral(A.T, np.outer(g, g), dt) * intensity


def catalogue():
    """The faults, in the analysis's order: (sensor, kind, magnitude, its multiple of sigma;
    "-" and 0 for the kinds without one)."""
    for sensor in fb.SENSORS:
        for kind in KINDS:
            mags = MAGNITUDES if kind in ("bias", "drift", "gain") else {"-": 0.0}
            for mag, mult in mags.items():
                yield sensor, kind, mag, mult


def fault_at(kind: str, size: float, t: int, dt: float, sigma: float) -> tuple:
    """The fault at tick ``t`` from its onset, f_t = k_t (c z_t) + f0_t (+ white noise of
    variance qn; ``held``: the value held from the onset): (k, f0, qn, held)."""
    if kind == "bias":
        return 0.0, size, 0.0, False
    if kind == "drift":
        return 0.0, size * t * dt / DRIFT_S, 0.0, False
    if kind == "gain":
        return size, 0.0, 0.0, False
    if kind == "stuck":
        return -1.0, 0.0, 0.0, True
    if kind == "noise":
        return 0.0, 0.0, (NOISE_FACTOR * sigma) ** 2 - sigma ** 2, False
    if kind == "dropout":
        return (-1.0 if t % DROPOUT_PERIOD < DROPOUT_ON else 0.0), 0.0, 0.0, False
    return 0.0, 0.0, 0.0, False


def propagate(gen: fb.Generator, A_f: np.ndarray, case: Case, sig: dict, sensor: str, kind: str,
              size: float, ticks: int, dt: float, sigma: float,
              clip_sq: float = math.inf, check: bool = True) -> np.ndarray:
    """Per tick from the fault's onset, the EWMA tests' expected inputs for one filter:
    column 0 E[nu' S^-1 nu] / m (the bank's whitened test, its clip ignored), then
    E[min(nu_j^2 / S_jj, clip_sq)] per channel (the ECU's innovation tests, each tick's
    square clipped as theirs: what keeps a fault of a few samples, a spike or a dropout's
    burst, from crossing at once)."""
    from scipy.linalg import expm, solve_discrete_lyapunov

    n = gen.phi.shape[0]
    m = gen.H.shape[0]
    nz = 5 + n + 1                       # the car, the filter's error, a held value (stuck)
    phi_cl = expm(case.A_cl * dt)
    a_e = gen.error_phi
    M = np.zeros((nz, nz))
    M[:5, :5] = phi_cl
    M[5:5 + n, 5:5 + n] = a_e
    M[-1, -1] = 1.0
    Q = np.zeros((nz, nz))
    Q[:5 + n, :5 + n] = _joint_noise(case.A_cl, A_f, n, dt, case.intensity)
    pk = gen.phi @ gen.K
    bf = gen.gamma_force - pk @ gen.D_force       # the force error's way in (white)
    Q[5:5 + n, 5:5 + n] += (gen.q_fixed + pk @ gen.r0 @ pk.T
                            + case.var_force * np.outer(bf, bf))
    Rnu = gen.r0 + case.var_force * np.outer(gen.D_force, gen.D_force)
    # the cross-covariance of nu_t's noise with the error's next step (v and the force error
    # enter both) does not change nu_t's own covariance: it is left out
    S = gen.innovation_cov(case.intensity, case.var_force)
    S_inv = np.linalg.inv(S)
    b, d = gen.fault_input(sensor)
    c = np.zeros(nz)
    c[:5] = sig[sensor]
    # the stationary start: the car and the filter's error, the held value y(0)
    Sig = solve_discrete_lyapunov(M[:-1, :-1], Q[:-1, :-1])
    Sig = np.pad(Sig, ((0, 1), (0, 1)))
    Sig[-1, :-1] = Sig[:-1, -1] = c[:-1] @ Sig[:-1, :-1]
    Sig[-1, -1] = c[:-1] @ Sig[:-1, :-1] @ c[:-1]
    Hz = np.zeros((m, nz))
    Hz[:, 5:5 + n] = gen.H
    healthy = Hz @ Sig @ Hz.T + Rnu
    # (off the filter's design speed its road pole is not the car's: ``check`` is off and
    # the healthy statistic is not 1, where the tests start: ``_filter_result``)
    if check and not np.allclose(healthy, S, rtol=1e-6, atol=1e-12 * np.max(np.abs(S))):
        raise AssertionError(f"{gen.blind}: the joint system's innovation covariance is not "
                             f"the filter's own (max rel {np.max(np.abs(healthy / S - 1)):.2e})")
    mu = np.zeros(nz)
    out = np.empty((ticks, 1 + m))
    s_diag = np.diag(S)
    for t in range(ticks):
        k, f0, qn, held = fault_at(kind, size, t, dt, sigma)
        fz = k * c
        if held:
            fz = fz.copy()
            fz[-1] = 1.0
        Hf = Hz + np.outer(d, fz)
        mean_nu = Hf @ mu + d * f0
        cov_nu = Hf @ Sig @ Hf.T + Rnu + qn * np.outer(d, d)
        out[t, 0] = (float(np.sum(S_inv * cov_nu)) + float(mean_nu @ S_inv @ mean_nu)) / m
        out[t, 1:] = clipped_square(mean_nu / np.sqrt(s_diag), np.diag(cov_nu) / s_diag,
                                    clip_sq)
        # step: the error takes b f_t
        Mt = M.copy()
        Mt[5:5 + n, :] += np.outer(b, fz)
        mu = Mt @ mu
        mu[5:5 + n] += b * f0
        Sig = Mt @ Sig @ Mt.T + Q
        Sig[5:5 + n, 5:5 + n] += qn * np.outer(b, b)
    return out


def clipped_square(mu, var, clip_sq: float):
    """E[min(Z^2, c^2)] for Z ~ N(mu, var), elementwise: the truncated second moment inside
    |Z| < c plus c^2 times the probability outside."""
    from scipy.special import ndtr

    mu, var = np.asarray(mu, dtype=float), np.asarray(var, dtype=float)
    if not math.isfinite(clip_sq):
        return var + mu * mu
    c = math.sqrt(clip_sq)
    sd = np.sqrt(np.maximum(var, 1e-300))
    a, b = (-c - mu) / sd, (c - mu) / sd
    pa, pb = np.exp(-0.5 * a * a) / math.sqrt(2 * math.pi), np.exp(-0.5 * b * b) / math.sqrt(
        2 * math.pi)
    inside = ndtr(b) - ndtr(a)
    m2 = (mu * mu * inside + 2.0 * mu * sd * (pa - pb)
          + var * (inside + a * pa - b * pb))
    return m2 + clip_sq * (1.0 - inside)


def scatter(lam: float, m: int) -> float:
    """The standard deviation of a healthy test's EWMA (weight ``lam``) of nu' S^-1 nu / m,
    chi2_m / m per tick for white Gaussian innovations (variance 2 / m)."""
    return math.sqrt(lam / (2.0 - lam) * 2.0 / m)


def crossing(stat: np.ndarray, lam: float, level: float, start: float = 1.0) -> int | None:
    """The first tick the EWMA (from its healthy mean ``start``) of the expected statistic
    passes
    ``level``; None if it does not (``level``: the test's own, plus ``RELIABLE_SD`` of its
    scatter, where the analysis asks what a test reliably does)."""
    e = start
    for t, v in enumerate(stat):
        e += lam * (v - e)
        if e > level:
            return t
    return None


def fault_size(kind: str, sigma: float, rms: float, mult: float) -> float | None:
    """The fault's parameter for a magnitude of ``mult`` sigma: the bias, the drift's value at
    DRIFT_S, the gain's excess (g - 1: the signal's RMS moves by mult sigma); None where it
    has no magnitude (stuck, dropout: one each) or no signal to scale (a gain on a zero
    current)."""
    if kind in ("bias", "drift"):
        return mult * sigma
    if kind == "gain":
        return mult * sigma / rms if rms > 0 else None
    return 0.0


def _case(cond: str, A5, B5, K, q: float, band: float) -> tuple:
    """The car under the law u = -K x on the road of intensity q: its Case (with the state's
    stationary covariance ``X``) and its force's RMS."""
    from scipy.linalg import solve_continuous_lyapunov

    A_cl = A5 - np.outer(B5, K)
    e = np.zeros(5)
    e[4] = 1.0
    X = solve_continuous_lyapunov(A_cl, -np.outer(e, e) * q)
    f_rms = math.sqrt(float(K @ X @ K))
    return Case(cond, A_cl, K, q, (f_rms * band) ** 2 / 12.0, X), f_rms


def _filter_result(gen: fb.Generator, A_f, case: Case, sig: dict, sensor: str, kind: str,
                   size: float, ticks: int, sigma: float, opts: DesignOptions,
                   exact: bool, h: np.ndarray) -> dict:
    """One filter's response to one fault: when its test reliably crosses (the bank's; the
    full filter's also per channel, the ECU's innovation tests) and where its EWMA ends;
    ``h``: the filter's healthy statistic (``propagate`` of no fault: 1 at the filter's
    design speed), where each EWMA starts."""
    from calib.fdi_design import chi2_level

    dt, alpha, clip = opts.dt_s, opts.fdi_false_alarm, opts.fdi_clip_sigmas ** 2
    lam, lam_bank = 2.0 / (opts.fdi_nis_window + 1), 2.0 / (opts.fdi_bank_window + 1)
    st = propagate(gen, A_f, case, sig, sensor, kind, size, ticks, dt, sigma, clip, exact)
    m = gen.H.shape[0]
    lvl = chi2_level(m * opts.fdi_bank_window, alpha)
    sure = lvl + RELIABLE_SD * scatter(lam_bank, m)
    r = {"cross_ms": _ms(crossing(st[:, 0], lam_bank, sure, h[0]), dt),
         "end": float(_ewma_end(st[:, 0], lam_bank)), "level": lvl}
    if gen.blind == "full":                 # the ECU's own tests, per channel
        sure1 = chi2_level(opts.fdi_nis_window, alpha) + RELIABLE_SD * scatter(lam, 1)
        r["channels"] = {ch: _ms(crossing(st[:, 1 + j], lam, sure1, h[1 + j]), dt)
                         for j, ch in enumerate(gen.reads) if opts.fdi_nis_verdicts[j]}
    return r


def analyse(cfg, opts: DesignOptions, grade: str, speed: float, progress=None) -> dict:
    """The whole analysis: {"filters", "faults": [row, ...]} (module doc)."""
    from calib.control_design import comfort_law
    from calib.model import filter_continuous
    from calib.iso8608 import GRADE_GQ_M3
    from calib.model import linear_model

    dt = opts.dt_s
    exact = abs(speed - NOMINAL_SPEED_MPS) < 1e-9    # the filters' road pole is the car's
    banks = {"comfort": fb.generators(cfg, opts),     # passive: the fail-safe's open bridge
             "passive": fb.generators(cfg, opts, bridge_open=True)}
    bank = banks["comfort"]
    A5, B5 = filter_continuous(cfg, speed)
    A7 = fb.winding_continuous(cfg, A5, B5)
    q = fb.road_intensity(cfg, opts, grade, speed)
    model = linear_model(cfg.vehicle, GRADE_GQ_M3[opts.akf_q_grade], NOMINAL_SPEED_MPS)
    k_comfort = np.asarray(comfort_law(cfg, opts, model), dtype=float)
    band = 1.0 / cfg.actuator.screw_efficiency - cfg.actuator.screw_efficiency
    alpha = opts.fdi_false_alarm
    rows = []
    conds = {}
    for cond in CONDITIONS:
        case, f_rms = _case(cond, A5, B5, k_comfort if cond == "comfort" else np.zeros(5), q,
                            band)
        sig = _signals(cfg, A5, B5, case.K)
        X = case.X
        rms = {s: math.sqrt(float(sig[s] @ X @ sig[s])) for s in fb.SENSORS}
        conds[cond] = {"force_rms_n": f_rms, "signal_rms": rms}
        starts: dict = {}                    # the healthy statistic per filter
        for sensor, kind, mag, mult in catalogue():
            sigma = fb.sensor_sigma(cfg, sensor)
            size = fault_size(kind, sigma, rms[sensor], mult)
            row = {"condition": cond, "sensor": sensor, "kind": kind, "magnitude": mag,
                   "size": size, "filters": {}}
            rows.append(row)
            if size is None or (kind == "dropout" and rms[sensor] == 0.0):
                row["note"] = "no signal: not a fault here"
                continue
            ticks = int(round(HORIZON_S.get(kind, HORIZON_DEFAULT_S) / dt))
            for name, gen in banks[cond].items():
                b, d = gen.fault_input(sensor)
                if not (np.any(b) or np.any(d)):
                    if sensor != name:
                        raise AssertionError(f"filter {name} does not see {sensor}")
                    row["filters"][name] = {"blind": True}
                    continue
                if sensor == name:
                    raise AssertionError(f"filter {name} sees the sensor it is blind to")
                A_f = A7 if gen.phi.shape[0] == 7 else A5
                if name not in starts:
                    starts[name] = propagate(gen, A_f, case, sig, sensor, "bias", 0.0, 1, dt,
                                             sigma, opts.fdi_clip_sigmas ** 2, exact)[0]
                row["filters"][name] = _filter_result(gen, A_f, case, sig, sensor, kind, size,
                                                      ticks, sigma, opts, exact,
                                                      starts[name])
            _judge(row, opts, cfg, sensor, kind)
            if progress:
                progress(row)
    return {"grade": grade, "speed_mps": speed, "alpha": alpha, "window": opts.fdi_nis_window,
            "bank": {k[9:]: getattr(opts, k) for k in ("fdi_bank_structure",
                                                        "fdi_bank_offset_walk_v",
                                                        "fdi_bank_window")},
            "conditions": conds, "faults": rows,
            "filters": {k: list(g.reads) for k, g in bank.items()}}


def _ms(t: int | None, dt: float) -> float | None:
    return None if t is None else round((t + 1) * dt * 1e3, 1)


def _ewma_end(stat: np.ndarray, lam: float) -> float:
    e = 1.0
    for v in stat:
        e += lam * (v - e)
    return e


def _judge(row: dict, opts: DesignOptions, cfg, sensor: str, kind: str) -> None:
    """Detection (the ECU's tests; a stuck channel: its flatline test), isolation (every filter
    that reads the sensor inconsistent, the blind one consistent) and their times."""
    from calib.fdi_design import flatline_ticks

    f = row["filters"]
    times = [t for t in f["full"].get("channels", {}).values() if t is not None]
    if kind == "stuck":
        c = getattr(cfg.sensors, fb.CHANNEL[sensor])
        n = flatline_ticks(c.noise_std, c.lsb, opts.fdi_false_alarm, opts.flatline_max_p)
        if n:
            row["flatline_ms"] = n * opts.dt_s * 1e3
            times.append(row["flatline_ms"])
    row["detect_ms"] = min(times) if times else None
    bank = [v["cross_ms"] for k, v in f.items() if k != "full" and not v.get("blind")
            and v["cross_ms"] is not None]
    row["bank_detect_ms"] = min(bank) if bank else None
    both = [t for t in (row["detect_ms"], row["bank_detect_ms"]) if t is not None]
    row["detected_ms"] = min(both) if both else None
    # a fault of sensor j cannot make the filter blind to j inconsistent: each inconsistent
    # filter clears its sensor; j is isolated once every other sensor is cleared
    row["candidates"] = [k for k in fb.SENSORS if f[k].get("blind")
                         or f[k]["cross_ms"] is None]
    t = [f[k]["cross_ms"] for k in fb.SENSORS if k != sensor and not f[k].get("blind")]
    row["isolable"] = row["candidates"] == [sensor]
    row["isolated_ms"] = max(t) if row["isolable"] else None
    if "flatline_ms" in row:               # a flatline names its channel
        row["isolable"] = True
        row["isolated_ms"] = min(x for x in (row["isolated_ms"], row["flatline_ms"])
                                 if x is not None)


def counts(rows: list[dict]) -> dict:
    """Faults (those with a signal to act on), detected, isolated; the issue's key faults:
    every large one, every bias and every stuck sensor."""
    rows = [r for r in rows if "note" not in r]
    key = [r for r in rows if r["magnitude"] == "large" or r["kind"] in ("bias", "stuck")]
    return {"faults": len(rows), "detected": sum(r.get("detected_ms") is not None for r in rows),
            "isolated": sum(bool(r.get("isolable")) for r in rows),
            "key": len(key), "key_isolated": sum(bool(r.get("isolable")) for r in key)}


def analyse_cached(cfg, opts: DesignOptions, grade: str, speed: float) -> dict:
    """``analyse`` through the design cache (``calib.cache``): the sensor campaign's faults
    and what it expects of them, once per car, road and design."""
    from calib import cache

    return cache.cached("isolability", (repr(cfg).encode(), repr(opts).encode(),
                                        grade.encode(), repr(float(speed)).encode()),
                        lambda: analyse(cfg, opts, grade, speed))
