"""Processor in the loop, step one: the C fixed-point path on a Cortex-M4F and a Cortex-M7
under QEMU, replaying the recorded traces of ``tests/test_c_parity.py`` (docs/pil.md).

    python -m tools.pil [--out DIR] [--targets m4f,m7] [--update] [--json]

For each target (``tools.pil_build.TARGETS``) and trace (the full road section's first 80 s;
the bump-stop drive, with its vehicle's tables) it builds the image, runs it on
``qemu-system-arm`` and requires the same integers as the Python fixed path on every tick;
then it reports the instructions per tick (exact, from the virtual clock: p50, p99, max, per
controller and in the crossfades), the stack fx_tick used, and the ECU's flash, RAM and
worst-case stack. Each runs again with the whole estimator in C (``tools.pil_cov``: double
on the M7, bit-exact with Python; float32 on the M4F, bit-exact with the host's float32 build,
its deviation from double measured; its cost over the M4F budget is reported, not failed:
the covariance side is the background task's). It checks the integer path against the M4F
budgets, and every figure against those pinned in
``tests/golden/pil.json`` (``--update`` rewrites them: a change says why in its commit).
Writes DIR/report.json (default out/pil). Exit 0 when all holds, 1 when a check fails,
2 when the toolchain is missing or a run breaks.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from firmware.params import CTRL_NAMES
from hil.cli import add_json_argument, emit, fail
from tools import pil_build as pb
from tools import pil_cov, pil_cover, pil_mix
from tools.c_build import GEN, bump_stop_trace, full_road_trace, sensor_fault_trace

ROOT = Path(__file__).resolve().parents[1]
PINNED = ROOT / "tests" / "golden" / "pil.json"
MAGIC = 0x214C4950
TRAILER = 6
# the M4F's budget (issue 42; docs/pil.md justifies the CPI behind the instructions)
BUDGET = {"tick_instructions": 11_200, "stack_bytes": 2048, "flash_bytes": 65536,
          "ram_bytes": 16384}
ASSUMED_CPI = 1.5   # 11,200 instructions = 10 % of 1 ms at 168 MHz / 1.5
RUN_TIMEOUT_S = 900
MIX_WINDOW = 300    # ticks from the middle of each controller's stretch, for the mix


def trace_array(rec) -> np.ndarray:
    """A record as the harness's trace.bin rows (fx_in_t's fields, int32)."""
    rows = [[-1 if v is None else v for v in i.counts] + list(i.k_q) + list(i.r_q)
            + [i.want, int(i.passive), int(i.fault), int(i.regen), int(i.reset)]
            for i, _ in rec]
    return np.asarray(rows, dtype="<i4")


def run_image(target: pb.Target, elf: Path, trace: np.ndarray, work: Path) -> dict:
    """One run of the image on QEMU over ``trace``: the outputs per tick, the SysTick counts
    and class of each tick, and the trailer's figures."""
    import subprocess

    work.mkdir(parents=True, exist_ok=True)
    (work / "trace.bin").write_bytes(trace.tobytes())
    try:
        res = subprocess.run(pb.qemu_command(target, elf), cwd=work, capture_output=True,
                             text=True, timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise pb.PilError(f"{target.name}: QEMU ran over {RUN_TIMEOUT_S} s") from None
    if res.returncode != 0:
        raise pb.PilError(f"{target.name}: the image exited with {res.returncode} "
                          f"(2: a file, 3: a fault) {res.stderr.strip()}")
    words = np.frombuffer((work / "out.bin").read_bytes(), dtype="<i4")
    if len(words) < TRAILER or words[-TRAILER] != MAGIC:
        raise pb.PilError(f"{target.name}: out.bin has no trailer (the run stopped early)")
    magic, ticks, stack, empty, state_b, in_b = (int(v) for v in words[-TRAILER:])
    rows = words[:-TRAILER].reshape(ticks, -1)
    return {"out": rows[:, :-2], "counts": rows[:, -2].astype(np.int64) - empty,
            "cls": rows[:, -1], "stack": stack, "state_bytes": state_b, "in_bytes": in_b}


def tick_instructions(counts: np.ndarray) -> np.ndarray:
    """SysTick counts as instructions; a count that is not within 40/128 of an instruction
    count would mean the clock is not what ``tools.pil_build`` says: an error."""
    exact = counts * pb.NS_PER_COUNT / 2 ** pb.ICOUNT_SHIFT
    n = np.rint(exact)
    if np.any(np.abs(exact - n) > pb.NS_PER_COUNT / 2 ** pb.ICOUNT_SHIFT + 1e-9):
        raise pb.PilError("SysTick counts are not whole instructions: the clock is not "
                          "25 MHz at -icount shift=7")
    return n.astype(np.int64)


def stats(v: np.ndarray) -> dict:
    return {"ticks": int(len(v)), "p50": int(np.percentile(v, 50, method="nearest")),
            "p99": int(np.percentile(v, 99, method="nearest")), "max": int(v.max())}


def cost(run: dict) -> dict:
    ins = tick_instructions(run["counts"])
    out = {"all": stats(ins)}
    xf = (run["cls"] & 16) != 0
    ctrl = run["cls"] & 15
    for c in sorted(set(ctrl[~xf].tolist())):
        out[CTRL_NAMES[c]] = stats(ins[(ctrl == c) & ~xf])
    if xf.any():
        out["crossfade"] = stats(ins[xf])
    return out


def first_difference(rec, got: np.ndarray):
    want = np.asarray([o for _, o in rec], dtype=np.int64)
    if want.shape != got.shape:
        return f"{got.shape[0]} ticks of {want.shape[1]} outputs back, {want.shape} wanted"
    bad = np.nonzero((want != got).any(axis=1))[0]
    if len(bad):
        k = int(bad[0])
        return f"tick {k}: target {got[k].tolist()} != Python {want[k].tolist()}"
    return None


def mix_windows(trace: np.ndarray) -> np.ndarray:
    """MIX_WINDOW ticks from the middle of each controller's stretch of the trace, one after
    the other (the mix of every controller in proportion, not the route's)."""
    want = trace[:, -5]          # (want, passive, fault, regen, reset: the last five)
    rows = []
    for c in sorted(set(want.tolist())):
        ks = np.nonzero(want == c)[0]
        rows.extend(ks[len(ks) // 2:len(ks) // 2 + MIX_WINDOW])
    return trace[rows]


def traces(work: Path, say) -> dict:
    say("recording the traces (hil sim, fixed point) ...")
    full, _ = full_road_trace()
    _, gen, bump = bump_stop_trace(work / "bump")
    return {"full_road_80s": (GEN, full), "bump_stops": (gen, bump),
            "sensor_out": (GEN, sensor_fault_trace())}


def measure(targets, work: Path, say=lambda s: None) -> dict:
    """Every target on every trace; the report (without the checks)."""
    recorded = traces(work, say)
    jobs = []
    for t in targets:
        for name, (gen, rec) in recorded.items():
            d = work / t.name / name
            say(f"{t.name}: building for {name}")
            jobs.append((t, name, rec, pb.build(t, d / "build", gen), d))
    say(f"running {len(jobs)} images on qemu-system-arm ...")

    def one(job):
        t, name, rec, elf, d = job
        r = run_image(t, elf, trace_array(rec), d / "run")
        say(f"{t.name} {name}: {len(rec)} ticks done")
        return job, r

    cov_jobs = pil_cov.build_all(targets, recorded, work, say)

    def one_cov(job):
        t, name, gen, rec, elf, d = job
        r = run_image(t, elf, pil_cov.cov_array(rec, t.name == "m7"), d / "run")
        say(f"{t.name} {name} with the estimator: {len(rec)} ticks done")
        return job, r

    with ThreadPoolExecutor(2) as pool:
        done = list(pool.map(one, jobs))
        cov_done = list(pool.map(one_cov, cov_jobs))
    say("the branches the traces take (host, gcov) ...")
    report = {"targets": {}, "coverage": pil_cover.coverage(recorded.values(), work / "cov")}
    m4 = [j for j in jobs if j[0].name == "m4f" and j[1] == "full_road_80s"]
    if m4:
        t, _, rec, elf, d = m4[0]
        say("m4f: the executed instruction mix (QEMU's block log) ...")
        report["m4f_cycles"] = pil_mix.measure(
            t, elf, mix_windows(trace_array(rec)), d / "mix",
            pil_mix.code_range(elf, "__ecu_code_start", "__ecu_code_end"))
    for (t, name, rec, elf, d), r in done:
        entry = report["targets"].setdefault(t.name, {"what": t.what, "machine": t.machine,
                                                      "traces": {}})
        entry["traces"][name] = {"bit_exact": first_difference(rec, r["out"]) is None,
                                 "difference": first_difference(rec, r["out"]),
                                 "instructions": cost(r), "stack_used_bytes": r["stack"]}
        if name == "full_road_80s":
            entry["sizes"] = pb.sizes(d / "build")
            entry["stack_worst"] = pb.worst_stack(d / "build")
            entry["state_bytes"], entry["in_bytes"] = r["state_bytes"], r["in_bytes"]
            entry["ram_bytes"] = (entry["sizes"]["static_ram"] + r["state_bytes"]
                                  + r["in_bytes"])
    est = report["estimator"] = {}
    for job, r in cov_done:
        t, name, gen, rec, elf, d = job
        entry = est.setdefault(t.name, {"what": t.what, "traces": {}})
        v = entry["traces"][name] = pil_cov.assess(job, r, work / "cov-host" / t.name)
        v["instructions"] = cost(r)
        if name == "full_road_80s":
            entry["sizes"] = pb.sizes(d / "build", pb.COV_SOURCES)
            entry["stack_worst"] = pb.worst_stack(d / "build", "fx_tick_cov", pb.COV_SOURCES)
            entry["ram_bytes"] = entry["sizes"]["static_ram"] + r["state_bytes"] + r["in_bytes"]
    if "m4f" in est:
        worst = max(v["instructions"]["all"]["max"] for v in est["m4f"]["traces"].values())
        est["m4f"]["over_budget"] = {
            "tick_instructions": max(0, worst - BUDGET["tick_instructions"]),
            "stack_bytes": max(0, est["m4f"]["stack_worst"]["bytes"] - BUDGET["stack_bytes"]),
            "flash_bytes": max(0, est["m4f"]["sizes"]["flash"] - BUDGET["flash_bytes"]),
            "ram_bytes": max(0, est["m4f"]["ram_bytes"] - BUDGET["ram_bytes"])}
    return report


def pinned_view(report: dict) -> dict:
    """The figures pinned in tests/golden/pil.json."""
    out = {}
    for name, e in report["targets"].items():
        out[name] = {"flash_bytes": e["sizes"]["flash"], "ram_bytes": e["ram_bytes"],
                     "stack_worst_bytes": e["stack_worst"]["bytes"],
                     "traces": {tr: {"instructions": v["instructions"],
                                     "stack_used_bytes": v["stack_used_bytes"]}
                                for tr, v in e["traces"].items()}}
    est = report.get("estimator", {})
    if est:
        out["estimator"] = {
            name: {"flash_bytes": e["sizes"]["flash"], "ram_bytes": e["ram_bytes"],
                   "stack_worst_bytes": e["stack_worst"]["bytes"],
                   "traces": {tr: {k: v[k] for k in ("instructions", "stack_used_bytes",
                                                      "float32_vs_double") if k in v}
                              for tr, v in e["traces"].items()}}
            for name, e in est.items()}
    return out


def checks(report: dict, pinned) -> list:
    """What fails: a difference from Python, a budget broken on the M4F, a pinned figure
    that moved."""
    bad = []
    for name, e in report["targets"].items():
        for tr, v in e["traces"].items():
            if not v["bit_exact"]:
                bad.append(f"{name} {tr}: not bit-exact ({v['difference']})")
    m4 = report["targets"].get("m4f")
    if m4:
        worst = max(v["instructions"]["all"]["max"] for v in m4["traces"].values())
        for key, got in (("tick_instructions", worst),
                         ("stack_bytes", m4["stack_worst"]["bytes"]),
                         ("flash_bytes", m4["sizes"]["flash"]), ("ram_bytes", m4["ram_bytes"])):
            if got > BUDGET[key]:
                bad.append(f"m4f: {key} {got} over the budget of {BUDGET[key]}")
    for name, e in report.get("estimator", {}).items():
        for tr, v in e["traces"].items():
            if not v["bit_exact"]:
                bad.append(f"{name} {tr} with the {v['build']} estimator: not bit-exact with "
                           f"{v['reference']} ({v['difference']})")
            if v.get("soft_double_calls"):
                bad.append(f"{name} {tr}: the float32 estimator calls software double "
                           f"routines {', '.join(v['soft_double_calls'])}")
    cyc = report.get("m4f_cycles")
    if cyc and cyc["cpi"] > ASSUMED_CPI:
        bad.append(f"m4f: the executed mix costs {cyc['cpi']:.2f} cycles an instruction, over "
                   f"the {ASSUMED_CPI} the instruction budget assumes")
    if pinned is not None:
        now = pinned_view(report)
        for name in now:
            if name in pinned and pinned[name] != now[name]:
                bad.append(f"{name}: the figures differ from {PINNED.name} (--update rewrites "
                           "it; say why in the commit)")
    return bad


def render(r: dict) -> None:
    for name, e in r["targets"].items():
        print(f"{name}: {e['what']} (qemu -M {e['machine']}); flash {e['sizes']['flash']} B, "
              f"RAM {e['ram_bytes']} B (state {e['state_bytes']} B), worst-case stack "
              f"{e['stack_worst']['bytes']} B ({' > '.join(e['stack_worst']['path'])})")
        for tr, v in e["traces"].items():
            print(f"  {tr}: {'bit-exact' if v['bit_exact'] else v['difference']}; stack used "
                  f"{v['stack_used_bytes']} B; instructions per tick:")
            for cls, s in v["instructions"].items():
                print(f"    {cls:10} {s['ticks']:6} ticks  p50 {s['p50']:6}  p99 {s['p99']:6}"
                      f"  max {s['max']:6}")
    pil_cov.render(r.get("estimator", {}))
    cov = r["coverage"]
    print(f"c/ecu_fx.c on the traces: {cov['lines_run']} of {cov['lines']} lines, "
          f"{cov['branch_edges_taken']} of {cov['branch_edges']} branch edges; never run: "
          + " | ".join(f"{n}: {t}" for n, t in cov["lines_never_run"].items()))
    cyc = r.get("m4f_cycles")
    if cyc:
        mix = ", ".join(f"{k} {100 * v:.1f} %" for k, v in cyc["mix"].items())
        print(f"m4f: {cyc['cpi']:.2f} cycles an instruction over {cyc['instructions']} executed "
              f"instructions (Cortex-M4 timings, pessimistic, zero wait states; {mix})")
    for line in r["failures"]:
        print(f"FAIL {line}")
    print(f"pil: {'PASS' if not r['failures'] else 'FAIL'}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.pil", description=__doc__.split("\n")[0])
    ap.add_argument("--out", metavar="DIR", default=str(ROOT / "out" / "pil"))
    ap.add_argument("--targets", default=",".join(pb.TARGETS),
                    help=f"comma-separated, of {', '.join(pb.TARGETS)} (default: both)")
    ap.add_argument("--update", action="store_true", help=f"rewrite {PINNED.relative_to(ROOT)}")
    add_json_argument(ap)
    args = ap.parse_args(argv)
    names = [n for n in args.targets.split(",") if n]
    unknown = [n for n in names if n not in pb.TARGETS]
    if unknown or not names:
        fail(f"--targets: unknown {', '.join(unknown) or '(none given)'}; "
             f"known: {', '.join(pb.TARGETS)}")
    out = Path(args.out)
    say = (lambda s: print(s, file=sys.stderr, flush=True))
    try:
        with tempfile.TemporaryDirectory(prefix="pil-") as tmp:
            report = measure([pb.TARGETS[n] for n in names], Path(tmp), say)
    except pb.PilError as exc:
        fail(str(exc))
    pinned = json.loads(PINNED.read_text()) if PINNED.is_file() else {}
    if args.update:
        pinned.update(pinned_view(report))
        PINNED.write_text(json.dumps(pinned, indent=1, sort_keys=True) + "\n")
    report["budget_m4f"] = BUDGET
    report["failures"] = checks(report, pinned if pinned else None)
    if not pinned:
        report["failures"].append(f"no pinned figures ({PINNED.name}): run with --update")
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=1) + "\n")
    emit(report, args.json, render)
    return 1 if report["failures"] else 0


if __name__ == "__main__":
    from hil.cli import run_main

    run_main(main)
