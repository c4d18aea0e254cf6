"""Golden traces: every scenario of ``tests/golden`` gives the pinned trace hash, bus-log hash
and report metrics (``tests/golden/README.md`` says what each covers). A change that alters
them on purpose rewrites ``golden.json`` (``python -m tests.golden --update``) in the same
commit and says why."""

import hashlib

import numpy as np
import pytest

from hil.validate.acceptance import GRADE_ACCURACY
from tests import golden
from tests.golden import ticks as per_tick

WANT = golden.load()


def test_every_scenario_is_pinned():
    assert [s.name for s in golden.SCENARIOS] == list(WANT)


@pytest.mark.golden
@pytest.mark.parametrize("name", [s.name for s in golden.SCENARIOS])
def test_golden_trace(name):
    trace = []
    s = golden.BY_NAME[name]
    cols = [] if s.per_tick else None
    got = golden.run(s, trace, cols)
    want = WANT[name]
    assert got["command"] == want["command"]
    # a per-tick trace names the first differing tick and field before any hash does
    problems = (per_tick.differences(per_tick.load(name), cols[0]) if s.per_tick else [])
    problems += golden.diff(want, got)
    assert not problems, f"{name} ({want['command']}):\n" + "\n".join(problems)
    if name == "full_road_section_auto":
        # the firmware's acceptance on this run (tests/test_sil_acceptance.py has the other
        # seeds and routes): grades right, one switch per grade change at most, bumpless
        from tests.test_sil_acceptance import assert_bumpless

        rep = got["report"]
        assert rep["grade_accuracy"] >= GRADE_ACCURACY
        assert rep["mode_switches"] <= rep["grade_changes"] + 1
        assert_bumpless(trace[0])


@pytest.mark.parametrize("name", [s.name for s in golden.SCENARIOS if s.per_tick])
def test_per_tick_trace_is_the_pinned_trace(name):
    """The stored per-tick trace is the one the pinned hash covers: its rows, packed again as
    the ECU node packs them, hash to golden.json's trace_sha256."""
    cols = per_tick.load(name)
    rows = np.empty(len(cols["tick"]), dtype=per_tick.DTYPE)
    for field, values in cols.items():
        rows[field] = values
    assert hashlib.sha256(rows.tobytes()).hexdigest() == WANT[name]["trace_sha256"]
    assert list(cols["tick"]) == list(range(len(rows)))


def test_per_tick_comparison_names_the_first_differing_tick_and_field():
    cols = per_tick.columns(bytes(per_tick.DTYPE.itemsize * 5))
    cols["tick"] = np.arange(5, dtype=cols["tick"].dtype)
    assert per_tick.decode(per_tick.encode(cols)).keys() == cols.keys()
    assert all((per_tick.decode(per_tick.encode(cols))[k] == v).all() for k, v in cols.items())
    got = {k: v.copy() for k, v in cols.items()}
    got["duty_q15"][3:] = [-7, 2]
    got["faults"][4] = 1
    assert per_tick.differences(cols, cols) == []
    assert per_tick.differences(cols, got) == [
        "first differing tick: 3",
        "duty_q15: first at tick 3 (row 3): want 0, got -7; 2 ticks differ, largest "
        "difference 7",
        "faults: first at tick 4 (row 4): want 0, got 1; 1 ticks differ, largest difference 1"]
    short = {k: v[:4] for k, v in cols.items()}
    assert per_tick.differences(cols, short)[0] == "ticks: want 5, got 4 (compared over the " \
                                                   "first 4)"


def test_the_comparison_sees_a_changed_metric():
    want = {"report": {"segments": [{"ratio": {"ba": 0.8}}]}, "trace_sha256": "ab"}
    got = {"report": {"segments": [{"ratio": {"ba": 0.8000000000000002}}]}, "trace_sha256": "ab"}
    assert golden.diff(want, got) == ["/report/segments[0]/ratio/ba: want 0.8, got "
                                      "0.8000000000000002"]
    assert golden.diff(want, want) == []
    assert golden.diff({"a": 1}, {"a": 1.0}) == ["/a: want 1, got 1.0"]
