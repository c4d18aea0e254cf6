"""Process helpers of the bench tests: a process's children and command line, from /proc (no
procps needed); a realtime run's verdict where only its timing may fail; a bench started
with its hub's URL."""

from contextlib import contextmanager
from pathlib import Path


def children(pid: int) -> list[int]:
    """Child PIDs from /proc (no procps needed)."""
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


# the checks of a realtime run that a loaded or slow host may fail (hil.report.verdict.run_checks)
REALTIME_TIMING = frozenset({"missed_deadline_ratio", "lost_frame_ratio", "failsafe_ratio",
                             "plant_fallback_ratio"})


def assert_only_timing_failed(returncode: int, rep: dict, timing=REALTIME_TIMING) -> None:
    """Every check of a run's report but the ``timing`` ones holds, and the verdict and the
    exit code say whether any failed."""
    failed = {c["name"] for c in rep["checks"] if not c["ok"]}
    assert failed <= timing, [c for c in rep["checks"] if not c["ok"]]
    assert rep["verdict"] == ("fail" if failed else "pass")
    assert returncode == (1 if failed else 0)


@contextmanager
def bench_run(root: Path, out: Path, *argv: str):
    """``python -m hil run ... --out OUT --json`` started: (the process, the hub's URL once it
    has printed its bus; None on a kernel bus such as vcan0). The body waits for it
    (``communicate``); a run still going when the body leaves (an assertion failed) is
    killed."""
    import re
    import subprocess
    import sys
    import time

    run = subprocess.Popen([sys.executable, "-m", "hil", "run", *argv, "--out", str(out),
                            "--json"], cwd=root, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        line = ""
        deadline = time.monotonic() + 300
        while not line.startswith("bus: ") and time.monotonic() < deadline:
            line = run.stderr.readline()
            assert line or run.poll() is None, "hil run ended before its bus came up"
        assert line.startswith("bus: "), "hil run printed no bus within 300 s"
        m = re.search(r"ws://127\.0\.0\.1:\d+/", line)
        yield run, m.group(0) if m else None
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
