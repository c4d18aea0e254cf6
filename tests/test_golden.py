"""Golden traces: every scenario of ``tests/golden`` gives the pinned trace hash, bus-log hash
and report metrics (``tests/golden/README.md`` says what each covers). A change that alters
them on purpose rewrites ``golden.json`` (``python -m tests.golden --update``) in the same
commit and says why."""

import pytest

from tests import golden

WANT = golden.load()


def test_every_scenario_is_pinned():
    assert [s.name for s in golden.SCENARIOS] == list(WANT)


@pytest.mark.golden
@pytest.mark.parametrize("name", [s.name for s in golden.SCENARIOS])
def test_golden_trace(name):
    trace = []
    got = golden.run(golden.BY_NAME[name], trace)
    want = WANT[name]
    assert got["command"] == want["command"]
    problems = golden.diff(want, got)
    assert not problems, f"{name} ({want['command']}):\n" + "\n".join(problems)
    if name == "full_road_section_auto":
        # the firmware's acceptance on this run (tests/test_sil_acceptance.py has the other
        # seeds and routes): grades right, one switch per grade change at most, bumpless
        from tests.test_sil_acceptance import assert_bumpless

        rep = got["report"]
        assert rep["grade_accuracy"] >= 0.95
        assert rep["mode_switches"] <= rep["grade_changes"] + 1
        assert_bumpless(trace[0])


def test_the_comparison_sees_a_changed_metric():
    want = {"report": {"segments": [{"ratio": {"ba": 0.8}}]}, "trace_sha256": "ab"}
    got = {"report": {"segments": [{"ratio": {"ba": 0.8000000000000002}}]}, "trace_sha256": "ab"}
    assert golden.diff(want, got) == ["/report/segments[0]/ratio/ba: want 0.8, got "
                                      "0.8000000000000002"]
    assert golden.diff(want, want) == []
    assert golden.diff({"a": 1}, {"a": 1.0}) == ["/a: want 1, got 1.0"]
