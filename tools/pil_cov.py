"""The whole estimator in C on the targets (``tools.pil``; docs/pil.md): the covariance side
of the filter (``c/akf_cov.c``) with the integer path, fed only the counts, the road's
process-noise intensity and the supervisor's flags of each recorded tick (``fx_tick_cov``).

In double on the Cortex-M7 it must give the Python path's bits: the outputs, the Q gain and the
float gain K on every tick. In float32 on the Cortex-M4F it must give the host's float32 build's
bits (the same C, so the port is exact) and call no software double routine; its deviation
from double (the Python path) is measured: ticks that differ and by how much."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np

from firmware.fx.tables import F_FORCE, STATE_FRAC
from tools import pil_build as pb
from tools.c_build import compile_c, parse_cov_output, replay_cov_input, replay_sources

N_OUT = 12           # duty force x[5] resid[3] integ voltage (tools.c_build.replay_input's)
M = 3
COV_TARGET_BUILD = {"m4f": "float32", "m7": "double"}


def cov_array(rec, double: bool) -> np.ndarray:
    """The record as c/pil/harness.c's PIL_COV rows: counts[4], q_road as the bytes of the
    target's akf_real in two words, flags want passive fault regen."""
    q = np.zeros((len(rec), 2), dtype="<i4")     # (float32: the first word, the second 0)
    qv = np.asarray([i.q_road for i, _ in rec], dtype="<f8" if double else "<f4")
    q[:, :qv.itemsize // 4] = qv.view("<i4").reshape(len(rec), -1)
    head = [[-1 if v is None else v for v in i.counts] for i, _ in rec]
    tail = [[i.cov_flags, i.want, int(i.passive), int(i.fault), int(i.regen)] for i, _ in rec]
    return np.concatenate([np.asarray(head, dtype="<i4"), q, np.asarray(tail, dtype="<i4")],
                          axis=1)


def split(out: np.ndarray, double: bool) -> tuple:
    """A PIL_COV run's rows as (outputs, Q gain, the float gain K as float64)."""
    k = out[:, N_OUT + 5 * M:]
    K = (k.copy().view("<f8") if double else k[:, :5 * M].copy().view("<f4")).astype(float)
    return out[:, :N_OUT], out[:, N_OUT:N_OUT + 5 * M], K


def host_float32(gen: Path, rec, work: Path) -> tuple:
    """The host's float32 build of the same C over ``rec``: (outputs, Q gain, K)."""
    work.mkdir(parents=True, exist_ok=True)
    exe = compile_c(work / "replay_f32", replay_sources(gen), "-DAKF_FLOAT", gen=gen)
    res = subprocess.run([str(exe), "--cov"], input=replay_cov_input(rec), capture_output=True,
                         text=True, check=True)
    outs, kq, _, kf = parse_cov_output(res.stdout, M)
    return np.asarray(outs), np.asarray(kq), np.asarray(kf)


def _first(bad: np.ndarray, what: str):
    k = np.nonzero(bad)[0]
    return f"tick {int(k[0])}: {what} differ ({len(k)} ticks)" if len(k) else None


def compare(want: tuple, got: tuple) -> str | None:
    """The first tick where (outputs, Q gain, K bits) differ, or None."""
    for name, a, b in zip(("the outputs", "the Q gains", "the float gains' bits"), want, got):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape:
            return f"{name}: {b.shape} back, {a.shape} wanted"
        diff = (a.view(np.int64) != b.view(np.int64)) if a.dtype.kind == "f" else a != b
        msg = _first(diff.any(axis=1), name)
        if msg:
            return msg
    return None


def python_side(rec) -> tuple:
    return (np.asarray([o for _, o in rec], dtype=np.int64),
            np.asarray([i.k_q for i, _ in rec], dtype=np.int64),
            np.asarray([i.k_f for i, _ in rec], dtype=float))


def deviation(rec, got: tuple) -> dict:
    """float32 against double (the Python path): per state, the force and the duty, the ticks
    that differ and the largest difference (states in SI units and in units of the state's
    RMS over the trace); the gain's largest difference relative to its element's range."""
    want, _, kw = python_side(rec)
    out, _, kf = got
    rep = {"ticks": int(len(rec))}
    names = ("body_velocity", "wheel_velocity", "body_position", "wheel_position",
             "road_position")
    for i, name in enumerate(names):
        w = want[:, 2 + i] * 2.0 ** -STATE_FRAC[i]
        d = np.abs(out[:, 2 + i] * 2.0 ** -STATE_FRAC[i] - w)
        rms = float(np.sqrt(np.mean(w * w)))
        rep[name] = {"ticks_differ": int((d > 0).sum()), "max_abs": float(d.max()),
                     "rms_abs": float(np.sqrt(np.mean(d * d))), "state_rms": rms,
                     "max_in_state_rms": float(d.max() / rms) if rms > 0 else None}
    df = np.abs(out[:, 1] - want[:, 1]) * 2.0 ** -F_FORCE
    rep["force_n"] = {"ticks_differ": int((df > 0).sum()), "max_abs": float(df.max()),
                      "rms_abs": float(np.sqrt(np.mean(df * df)))}
    dd = np.abs(out[:, 0] - want[:, 0])
    rep["duty_counts"] = {"ticks_differ": int((dd > 0).sum()), "max_abs": int(dd.max())}
    span = np.maximum(np.abs(kw).max(axis=0), 1e-300)
    rel = np.abs(kf - kw) / span
    rep["gain_max_in_element_range"] = float(rel.max())
    rep["gain_first_tick_over_1pct"] = int(np.argmax(rel.max(axis=1) > 0.01)) \
        if (rel.max(axis=1) > 0.01).any() else None
    return rep


def build_all(targets, recorded: dict, work: Path, say) -> list:
    jobs = []
    for t in targets:
        for name, (gen, rec) in recorded.items():
            d = work / f"{t.name}-cov" / name
            say(f"{t.name}: building for {name} with the {COV_TARGET_BUILD[t.name]} estimator")
            jobs.append((t, name, gen, rec, pb.build(t, d / "build", gen, cov=True), d))
    return jobs


def assess(job, run: dict, work: Path) -> dict:
    """One estimator image's run: exact against its reference, the cost, for the M4F the
    deviation from double and the software double routines its estimator object calls."""
    t, name, gen, rec, elf, d = job
    double = COV_TARGET_BUILD[t.name] == "double"
    got = split(run["out"], double)
    entry = {"build": COV_TARGET_BUILD[t.name], "stack_used_bytes": run["stack"]}
    if double:
        entry["reference"] = "the Python path (outputs, Q gain, float gain bits)"
        entry["difference"] = compare(python_side(rec), got)
    else:
        entry["reference"] = "the host's float32 build (outputs, Q gain, float gain bits)"
        entry["difference"] = compare(host_float32(gen, rec, work / f"host-{name}"), got)
        entry["float32_vs_double"] = deviation(rec, got)
        entry["soft_double_calls"] = pb.soft_double_calls(d / "build" / "akf_cov.o")
    entry["bit_exact"] = entry["difference"] is None
    return entry


def render(est: dict) -> None:
    """The estimator's lines of ``tools.pil``'s report."""
    for name, e in est.items():
        build = next(iter(e["traces"].values()))["build"]
        print(f"{name} with the {build} estimator (c/akf_cov.c): flash {e['sizes']['flash']} B, "
              f"RAM {e['ram_bytes']} B, worst-case stack {e['stack_worst']['bytes']} B")
        for tr, v in e["traces"].items():
            a = v["instructions"]["all"]
            exact = "bit-exact with " + v["reference"] if v["bit_exact"] else v["difference"]
            print(f"  {tr}: {exact}; instructions per tick p50 {a['p50']} p99 {a['p99']} "
                  f"max {a['max']}")
            dev = v.get("float32_vs_double")
            if dev:
                duty = dev["duty_counts"]
                print(f"    float32 against double: duty differs on {duty['ticks_differ']} of "
                      f"{dev['ticks']} ticks (max {duty['max_abs']} counts), force max "
                      f"{dev['force_n']['max_abs']:.1f} N, body velocity max "
                      f"{dev['body_velocity']['max_in_state_rms']:.2f} x its RMS")
        over = {k: v for k, v in e.get("over_budget", {}).items() if v}
        if over:
            print("  OVER the M4F budget with the estimator in the tick: "
                  + ", ".join(f"{k} by {v}" for k, v in over.items())
                  + " (reported, not failed: docs/pil.md)")
