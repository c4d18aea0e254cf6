"""Which single sensor faults the isolation bank can tell apart, and how fast: the analysis
of docs/diagnostics.md ("Isolability"), computed from the model.

    python -m tools.isolability [--vehicle FILE] [--grade B] [--speed 20] [--json OUT]

For each sensor (BA, WA, deflection, current), each fault (bias, drift, gain, stuck, noise x5,
an intermittent dropout) and two magnitudes (small 3 sigma, large 10 sigma of the sensor's own
noise; a drift reaches them in 10 s; a gain moves the signal's RMS by them), in comfort mode and
in the fail-safe (passive), it propagates the exact mean and covariance of every filter's
innovation (``calib.fdi_bank``) from the fault's onset: the car, the filter's error and the
fault as one linear system, the car in its stationary state at the onset. The expected
statistic of each test (the EWMA of the normalised squared innovations, W ticks) then gives
the time it crosses its level at the designed false-alarm rate: the mean detection time of
the ECU's tests and the time each bank filter turns inconsistent. A fault is isolable where
every filter that reads the sensor turns inconsistent and the one blind to it cannot (its
response is zero: checked). Exit 0 when every large fault that is isolable in structure is
isolated by the analysis within the horizon, 1 otherwise, 2 on bad input.

The expectation is of the statistic, not of its crossing time: a statistic whose mean just
reaches the level crosses it late or early by chance. The clip of one tick's square (at
``fdi_clip_sigmas``^2) is ignored: it matters only for faults far above the level.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
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


def propagate(gen: fb.Generator, A_f: np.ndarray, case: Case, sig: dict, sensor: str, kind: str,
              size: float, ticks: int, dt: float, sigma: float) -> np.ndarray:
    """Per tick from the fault's onset, the EWMA tests' expected inputs for one filter:
    column 0 E[nu' S^-1 nu] / m (the bank's whitened test), then E[nu_j^2] / S_jj per
    channel (the ECU's innovation tests)."""
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
    if not np.allclose(healthy, S, rtol=1e-6, atol=1e-12 * np.max(np.abs(S))):
        raise AssertionError(f"{gen.blind}: the joint system's innovation covariance is not "
                             f"the filter's own (max rel {np.max(np.abs(healthy / S - 1)):.2e})")
    mu = np.zeros(nz)
    out = np.empty((ticks, 1 + m))
    s_diag = np.diag(S)
    for t in range(ticks):
        # the fault f_t = k_t (c z_t) + f0_t (+ white noise of variance qn)
        k, f0, qn = 0.0, 0.0, 0.0
        held = False
        if kind == "bias":
            f0 = size
        elif kind == "drift":
            f0 = size * t * dt / DRIFT_S
        elif kind == "gain":
            k = size
        elif kind == "stuck":
            k, held = -1.0, True
        elif kind == "noise":
            qn = ((NOISE_FACTOR * sigma) ** 2 - sigma ** 2)
        elif kind == "dropout":
            k = -1.0 if t % DROPOUT_PERIOD < DROPOUT_ON else 0.0
        fz = k * c
        if held:
            fz = fz.copy()
            fz[-1] = 1.0
        Hf = Hz + np.outer(d, fz)
        mean_nu = Hf @ mu + d * f0
        cov_nu = Hf @ Sig @ Hf.T + Rnu + qn * np.outer(d, d)
        out[t, 0] = (float(np.sum(S_inv * cov_nu)) + float(mean_nu @ S_inv @ mean_nu)) / m
        out[t, 1:] = (np.diag(cov_nu) + mean_nu ** 2) / s_diag
        # step: the error takes b f_t
        Mt = M.copy()
        Mt[5:5 + n, :] += np.outer(b, fz)
        mu = Mt @ mu
        mu[5:5 + n] += b * f0
        Sig = Mt @ Sig @ Mt.T + Q
        Sig[5:5 + n, 5:5 + n] += qn * np.outer(b, b)
    return out


def crossing(stat: np.ndarray, lam: float, level: float) -> int | None:
    """The first tick the EWMA (from its healthy mean 1) of the expected statistic passes
    ``level``; None if it does not."""
    e = 1.0
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


def analyse(cfg, opts: DesignOptions, grade: str, speed: float, progress=None) -> dict:
    """The whole analysis: {"filters", "faults": [row, ...]} (module doc)."""
    from scipy.linalg import solve_continuous_lyapunov

    from calib.control_design import comfort_law
    from calib.fdi_design import chi2_level
    from calib.model import filter_continuous
    from calib.iso8608 import GRADE_GQ_M3
    from calib.model import linear_model

    dt = opts.dt_s
    bank = fb.generators(cfg, opts)
    A5, B5 = filter_continuous(cfg, speed)
    A7 = fb.winding_continuous(cfg, A5, B5)
    q = fb.road_intensity(cfg, opts, grade, speed)
    model = linear_model(cfg.vehicle, GRADE_GQ_M3[opts.akf_q_grade], NOMINAL_SPEED_MPS)
    k_comfort = np.asarray(comfort_law(cfg, opts, model), dtype=float)
    band = 1.0 / cfg.actuator.screw_efficiency - cfg.actuator.screw_efficiency
    lam = 2.0 / (opts.fdi_nis_window + 1)
    lam_bank = 2.0 / (opts.fdi_bank_window + 1)
    alpha = opts.fdi_false_alarm
    level1 = chi2_level(opts.fdi_nis_window, alpha)
    rows = []
    conds = {}
    for cond in CONDITIONS:
        K = k_comfort if cond == "comfort" else np.zeros(5)
        A_cl = A5 - np.outer(B5, K)
        e = np.zeros(5)
        e[4] = 1.0
        X = solve_continuous_lyapunov(A_cl, -np.outer(e, e) * q)
        f_rms = math.sqrt(float(K @ X @ K))
        case = Case(cond, A_cl, K, q, (f_rms * band) ** 2 / 12.0)
        sig = _signals(cfg, A5, B5, K)
        rms = {s: math.sqrt(float(sig[s] @ X @ sig[s])) for s in fb.SENSORS}
        conds[cond] = {"force_rms_n": f_rms, "signal_rms": rms}
        for sensor in fb.SENSORS:
            sigma = fb.sensor_sigma(cfg, sensor)
            for kind in KINDS:
                mags = MAGNITUDES if kind in ("bias", "drift", "gain") else {"-": 0.0}
                for mag, mult in mags.items():
                    size = fault_size(kind, sigma, rms[sensor], mult)
                    row = {"condition": cond, "sensor": sensor, "kind": kind, "magnitude": mag,
                           "size": size, "filters": {}}
                    rows.append(row)
                    if size is None or (kind == "dropout" and rms[sensor] == 0.0):
                        row["note"] = "no signal: not a fault here"
                        continue
                    ticks = int(round(HORIZON_S.get(kind, HORIZON_DEFAULT_S) / dt))
                    for name, gen in bank.items():
                        b, d = gen.fault_input(sensor)
                        if not (np.any(b) or np.any(d)):
                            if sensor != name:
                                raise AssertionError(f"filter {name} does not see {sensor}")
                            row["filters"][name] = {"blind": True}
                            continue
                        if sensor == name:
                            raise AssertionError(f"filter {name} sees the sensor it is blind to")
                        A_f = A7 if gen.phi.shape[0] == 7 else A5
                        st = propagate(gen, A_f, case, sig, sensor, kind, size, ticks, dt, sigma)
                        m = gen.H.shape[0]
                        lvl = chi2_level(m * opts.fdi_bank_window, alpha)
                        r = {"cross_ms": _ms(crossing(st[:, 0], lam_bank, lvl), dt),
                             "end": float(_ewma_end(st[:, 0], lam_bank)), "level": lvl}
                        if name == "full":          # the ECU's own tests, per channel
                            r["channels"] = {
                                ch: _ms(crossing(st[:, 1 + j], lam, level1), dt)
                                for j, ch in enumerate(gen.reads)
                                if opts.fdi_nis_verdicts[j]}
                        row["filters"][name] = r
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


def _cell(v) -> str:
    return "–" if v is None else f"{v:g}"


def render(res: dict, vehicle: str) -> str:
    """The analysis as Markdown: per condition a table of every fault, then the counts."""
    out = [f"# Isolability: {vehicle}, grade {res['grade']} at {res['speed_mps']:g} m/s",
           "", f"False-alarm rate {res['alpha']:g} per window; the ECU's tests W = "
           f"{res['window']} ticks; the bank: {res['bank']}.", "",
           "Filters (blind to: reads): " + "; ".join(
               f"{k}: {', '.join(v)}" for k, v in res["filters"].items()), ""]
    for cond, info in res["conditions"].items():
        rows = [r for r in res["faults"] if r["condition"] == cond]
        out += [f"## {cond} (force RMS {info['force_rms_n']:.0f} N)", "",
                "| sensor | fault | size | ECU tests ms | bank ms | isolated ms | "
                "candidates left |", "|---|---|---|---|---|---|---|"]
        for r in rows:
            size = "–" if r["size"] is None else f"{r['magnitude']} ({r['size']:.3g})" \
                if r["magnitude"] != "-" else "–"
            cand = ", ".join(r.get("candidates", [])) if not r.get("isolable") else ""
            out.append(f"| {r['sensor']} | {r['kind']} | {size} | {_cell(r.get('detect_ms'))} | "
                       f"{_cell(r.get('bank_detect_ms'))} | {_cell(r.get('isolated_ms'))} | "
                       f"{r.get('note', cand)} |")
        c = counts(rows)
        out += ["", f"Detected {c['detected']} of {c['faults']}, isolated {c['isolated']} "
                f"({c['isolated'] / c['faults']:.0%}); large, bias and stuck faults isolated "
                f"{c['key_isolated']} of {c['key']}.", ""]
    return "\n".join(out)


def counts(rows: list[dict]) -> dict:
    """Faults (those with a signal to act on), detected, isolated; the issue's key faults:
    every large one, every bias and every stuck sensor."""
    rows = [r for r in rows if "note" not in r]
    key = [r for r in rows if r["magnitude"] == "large" or r["kind"] in ("bias", "stuck")]
    return {"faults": len(rows), "detected": sum(r.get("detected_ms") is not None for r in rows),
            "isolated": sum(bool(r.get("isolable")) for r in rows),
            "key": len(key), "key_isolated": sum(bool(r.get("isolable")) for r in key)}


def main(argv: list[str] | None = None) -> int:
    from calib.errors import ConfigError
    from calib.iso8608 import GRADE_GQ_M3
    from hil.config import default_vehicle, load_vehicle

    ap = argparse.ArgumentParser(prog="python -m tools.isolability", description=__doc__.split(
        "\n\n")[0])
    ap.add_argument("--vehicle", help="vehicle TOML (default: Table 3's car)")
    ap.add_argument("--grade", default="B", help="the road's ISO 8608 grade (default B)")
    ap.add_argument("--speed", type=float, default=20.0, help="m/s (default 20)")
    d = DesignOptions()
    ap.add_argument("--structure", default=d.fdi_bank_structure, choices=("voltage", "force"),
                    help="the bank's structure (DesignOptions.fdi_bank_structure)")
    ap.add_argument("--walk", type=float, default=d.fdi_bank_offset_walk_v,
                    help="the winding model's voltage offset walk, V/sqrt(s)")
    ap.add_argument("--window", type=int, default=d.fdi_bank_window,
                    help="the bank's EWMA window, ticks")
    ap.add_argument("--out", help="write the Markdown report here (default: stdout)")
    ap.add_argument("--json", help="write the results as JSON here")
    a = ap.parse_args(argv)
    if a.grade not in GRADE_GQ_M3 or not 0.5 <= a.speed <= 70.0:
        print(f"isolability: grade must be one of {''.join(GRADE_GQ_M3)} and speed within "
              f"0.5-70 m/s, got {a.grade!r}, {a.speed}", file=sys.stderr)
        return 2
    try:
        cfg = load_vehicle(a.vehicle) if a.vehicle else default_vehicle()
        opts = dataclasses.replace(DesignOptions(), fdi_bank_structure=a.structure,
                                   fdi_bank_offset_walk_v=a.walk, fdi_bank_window=a.window)
        fb.check_options(opts)
    except (ConfigError, ValueError) as e:
        print(f"isolability: {e}", file=sys.stderr)
        return 2
    n = [0]

    def progress(row):
        n[0] += 1
        print(f"\r{n[0]} faults analysed ({row['condition']}, {row['sensor']} {row['kind']})"
              + " " * 10, end="", file=sys.stderr, flush=True)
    try:
        res = analyse(cfg, opts, a.grade, a.speed, progress)
    except AssertionError as e:              # a self-check of the analysis failed
        print(f"\nisolability: FAIL: {e}", file=sys.stderr)
        return 1
    print(file=sys.stderr)
    text = render(res, a.vehicle or "table3.toml")
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text + "\n")
    else:
        print(text)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1, sort_keys=True)
    c = [counts([r for r in res["faults"] if r["condition"] == cond])
         for cond in res["conditions"]]
    print("isolability: PASS (self-checks held): " + "; ".join(
        f"{cond} {x['isolated']}/{x['faults']} isolated" for cond, x in zip(res["conditions"], c)),
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
