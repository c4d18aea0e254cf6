"""Processor in the loop (tools/pil.py, make pil): the C core on a Cortex-M4F and a Cortex-M7
under QEMU, bit-exact with the Python fixed path on the parity traces, its figures pinned in
tests/golden/pil.json; and the parts the verdict rests on (the clock's conversion, the stack
bound over the call graph, the checks)."""

import json
import shutil

import numpy as np
import pytest

from tools import pil
from tools import pil_build as pb
from tools import pil_mix

HAVE_TOOLS = all(shutil.which(t) for t in ("arm-none-eabi-gcc", "qemu-system-arm"))
needs_tools = pytest.mark.skipif(not HAVE_TOOLS, reason="Debian's gcc-arm-none-eabi, "
                                 "picolibc-arm-none-eabi and qemu-system-arm are not installed "
                                 "(as root: make pil-setup; .ci/run installs them)")


@needs_tools
@pytest.mark.slow
def test_both_targets_are_bit_exact_on_every_trace_and_the_figures_are_the_pinned_ones(
        tmp_path):
    rc = pil.main(["--out", str(tmp_path), "--json"])
    rep = json.loads((tmp_path / "report.json").read_text())
    assert set(rep["targets"]) == {"m4f", "m7"}
    len_of = {"full_road_80s": 80_000, "bump_stops": 15_000, "sensor_out": 6_000}
    for name, e in rep["targets"].items():
        assert set(e["traces"]) == {"full_road_80s", "bump_stops", "sensor_out"}
        for tr, v in e["traces"].items():
            assert v["bit_exact"], (name, tr, v["difference"])
        full = e["traces"]["full_road_80s"]["instructions"]
        # every controller of the route ran, and the crossfades between them
        assert set(full) >= {"all", "bppid", "lqr", "galqr", "regen", "crossfade"}, full
        assert full["all"]["ticks"] == 80_000
        assert sum(s["ticks"] for k, s in full.items() if k != "all") == 80_000
        # the observed stack is within the call graph's bound
        assert 0 < e["traces"]["full_road_80s"]["stack_used_bytes"] <= e["stack_worst"]["bytes"]
    # the whole estimator in C (c/akf_cov.c): double on the M7 bit-exact with Python, float32
    # on the M4F bit-exact with the host's float32 build, no software double in it, its
    # deviation from double measured on every trace and its cost against the budget reported
    est = rep["estimator"]
    assert est["m7"]["traces"].keys() == est["m4f"]["traces"].keys() == e["traces"].keys()
    for name, e in est.items():
        for tr, v in e["traces"].items():
            assert v["bit_exact"], (name, tr, v["difference"])
            assert v["instructions"]["all"]["ticks"] == len_of[tr]
            # the estimator costs more than the integer path alone, on every tick class
            assert (v["instructions"]["all"]["p50"]
                    > rep["targets"][name]["traces"][tr]["instructions"]["all"]["p50"])
    assert est["m7"]["traces"]["full_road_80s"]["build"] == "double"
    for tr, v in est["m4f"]["traces"].items():
        assert v["build"] == "float32" and v["soft_double_calls"] == []
        dev = v["float32_vs_double"]
        assert dev["ticks"] == len_of[tr] and 0 < dev["duty_counts"]["ticks_differ"] <= len_of[tr]
    worst = max(v["instructions"]["all"]["max"] for v in est["m4f"]["traces"].values())
    assert est["m4f"]["over_budget"]["tick_instructions"] == max(
        0, worst - pil.BUDGET["tick_instructions"])
    # the mix was read off the executed code, and the host's coverage of the same traces
    cyc = rep["m4f_cycles"]
    assert cyc["instructions"] > 100_000 and 1.0 < cyc["cpi"] <= pil.ASSUMED_CPI, cyc
    assert abs(sum(cyc["mix"].values()) - 1.0) < 1e-9
    cov = rep["coverage"]
    assert cov["branch_edges"] > 100 and 0 < cov["branch_edges_taken"] < cov["branch_edges"]
    assert cov["lines_run"] + len(cov["lines_never_run"]) == cov["lines"]
    assert rep["failures"] == [] and rc == 0, rep["failures"]


def test_systick_counts_convert_to_whole_instructions():
    # at 128 ns an instruction and 40 ns a count, n instructions take floor or ceil 3.2 n counts
    n = np.arange(1, 5000)
    for phase in (0, 17, 39):
        counts = (phase + 128 * n) // 40 - phase // 40
        assert (pil.tick_instructions(counts) == n).all()
    with pytest.raises(pb.PilError, match="not whole instructions"):
        pil.tick_instructions(np.array([8]))      # 8 counts = 2.5 instructions: impossible


def test_the_mix_costs_each_instruction_and_a_taken_branch_its_refill(tmp_path):
    log = tmp_path / "q.log"
    log.write_text("----------------\nIN: f\n"
                   "0x00000100:  b538       push     {r3, r4, r5, lr}\n"
                   "0x00000102:  6830       ldr      r0, [r6]\n"
                   "0x00000104:  d001       beq      #0x10a\n\n"
                   "----------------\nIN: f\n"
                   "0x0000010a:  fb81 2300  smull    r2, r3, r1, r0\n"
                   "0x0000010e:  bd38       pop      {r3, r4, r5, pc}\n\n"
                   "Trace 0: 0x1 [00000000/00000100/00000010/ff020200] f\n"
                   "Trace 0: 0x1 [00000000/0000010a/00000010/ff020200] f\n"
                   "Trace 0: 0x1 [00000000/00000100/00000010/ff020200] f\n"
                   "Trace 0: 0x1 [00000000/00000106/00000010/ff020200] f\n")
    mix, cycles = pil_mix.parse(log)
    assert mix == {"load/store multiple": 3, "load/store": 2, "branch": 2, "multiply": 1}
    # push 5 + ldr 2 + beq 1, taken (+3); smull 1 + pop 5, returning (+3); again, not taken
    assert cycles == (5 + 2 + 1 + 3) + (1 + 5 + 3) + (5 + 2 + 1)


def _ci(tmp_path, name, nodes, edges):
    lines = [f'node: {{ title: "{t}" label: "{t}\\nx.c:1:1\\n{b} bytes ({k})" }}'
             for t, b, k in nodes]
    lines += [f'edge: {{ sourcename: "{a}" targetname: "{b}" }}' for a, b in edges]
    (tmp_path / name).write_text("graph: {\n" + "\n".join(lines) + "\n}\n")


def test_the_worst_stack_is_the_deepest_path_and_says_what_it_cannot_bound(tmp_path):
    _ci(tmp_path, "ecu_fx.ci", [("fx_tick", 24, "static"), ("a", 100, "static"),
                                ("b", 40, "static"), ("c", 80, "bounded")],
        [("fx_tick", "a"), ("fx_tick", "b"), ("b", "c"), ("a", "memset")])
    _ci(tmp_path, "ecu_tables.ci", [], [])
    got = pb.worst_stack(tmp_path)
    assert got["bytes"] == 24 + 40 + 80 and got["path"] == ["fx_tick", "b", "c"]
    assert got["outside_the_graph"] == ["memset"] and got["not_static"] == ["c"]
    _ci(tmp_path, "ecu_fx.ci", [("fx_tick", 24, "static"), ("a", 8, "static")],
        [("fx_tick", "a"), ("a", "fx_tick")])
    with pytest.raises(pb.PilError, match="recursion"):
        pb.worst_stack(tmp_path)


def _report(max_ins=5000, stack=300, exact=True):
    tr = {"bit_exact": exact, "difference": None if exact else "tick 3: ...",
          "instructions": {"all": {"ticks": 10, "p50": 1, "p99": 2, "max": max_ins}},
          "stack_used_bytes": 100}
    return {"targets": {"m4f": {"sizes": {"flash": 30000}, "ram_bytes": 600,
                                "stack_worst": {"bytes": stack}, "traces": {"t": tr}}}}


def test_the_checks_fail_on_a_difference_a_broken_budget_and_a_moved_figure():
    ok = _report()
    assert pil.checks(ok, pil.pinned_view(ok)) == []
    assert any("not bit-exact" in f for f in pil.checks(_report(exact=False), None))
    assert any("tick_instructions 11201" in f for f in pil.checks(_report(11201), None))
    assert any("stack_bytes 2049" in f for f in pil.checks(_report(stack=2049), None))
    moved = pil.checks(_report(5001), pil.pinned_view(ok))
    assert len(moved) == 1 and "differ from pil.json" in moved[0]


def test_an_unknown_target_is_one_clear_error(capsys):
    with pytest.raises(SystemExit) as exc:
        pil.main(["--targets", "m0"])
    assert exc.value.code == 2
    assert "unknown m0" in capsys.readouterr().err
