"""The User-mode Linux launcher (``python -m hil vcan``, hil/transport/vcan.py), from the host: what a
command gets carried over and back, and that UML ends with nothing left behind. Marker
``needs_uml``: deselected where UML is not installed (tests/conftest.py says so)."""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.transport import vcan
from hil.transport.buslog import read_log
from tests.procutil import cmdline
def launch(*args, timeout=120, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil", "vcan", "--quiet", *args],
                          capture_output=True, text=True, timeout=timeout, **kw)


def _uml_procs(tag: str) -> list[int]:
    return [int(p.name) for p in Path("/proc").iterdir()
            if p.name.isdigit() and tag in cmdline(int(p.name))]


@pytest.mark.needs_uml
def test_the_launcher_carries_environment_directory_output_and_status(tmp_path):
    env = dict(os.environ, HIL_TEST_VALUE="carried over")
    script = ('echo "$HIL_TEST_VALUE"; pwd; cat /sys/class/net/vcan0/operstate; '
              'echo to-stderr >&2; exit 7')
    proc = launch("--", "sh", "-c", script, cwd=tmp_path, env=env)
    assert proc.returncode == 7, proc.stderr
    assert proc.stdout.splitlines() == ["carried over", str(tmp_path), "unknown"]
    assert proc.stderr.strip() == "to-stderr"
    assert launch("--", "sh", "-c", "kill -TERM $$").returncode == 128 + signal.SIGTERM


@pytest.mark.needs_uml
def test_the_launcher_records_with_candump(tmp_path):
    log = tmp_path / "c.log"
    proc = launch("--candump", str(log), "--", "cansend", "vcan0", "123#DEADBEEF")
    if shutil.which("cansend") is None:
        pytest.skip("Debian's can-utils (cansend) is not installed (as root: make vcan-setup; "
                    ".ci/run installs it)")
    assert proc.returncode == 0, proc.stderr
    assert [(f[1], f[2]) for f in read_log(log)] == [(0x123, bytes.fromhex("DEADBEEF"))]


@pytest.mark.needs_uml
@pytest.mark.parametrize("how", ["timeout", "ctrl-c", "sigterm"])
def test_the_launcher_ends_uml_on_timeout_and_signals_and_leaves_nothing(tmp_path, how):
    t0 = time.monotonic()
    argv = [sys.executable, "-m", "hil", "vcan", "--quiet", "--timeout",
            "8" if how == "timeout" else "600", "--", "sleep", "300"]
    sup = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    tag = f"umid=hil-{sup.pid}"
    deadline = time.monotonic() + 60
    while not _uml_procs(tag) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _uml_procs(tag), "UML did not start"
    if how != "timeout":
        time.sleep(3)                      # (booted, the command running)
        sup.send_signal(signal.SIGINT if how == "ctrl-c" else signal.SIGTERM)
    _, err = sup.communicate(timeout=60)
    assert sup.returncode == {"timeout": 124, "ctrl-c": 130, "sigterm": 143}[how], err
    assert ("timeout" if how == "timeout" else "interrupted") in err
    assert time.monotonic() - t0 < 40
    assert _uml_procs(tag) == []                              # UML and its helpers gone
    assert not list(Path(vcan.tempfile.gettempdir()).glob(f"hil-vcan-{sup.pid}-*"))


def test_the_launcher_without_uml_says_what_to_install(tmp_path):
    env = dict(os.environ, HIL_UML=str(tmp_path / "no-such-linux.uml"))
    env.pop(vcan.GUEST_MARK, None)
    proc = launch("--", "true", env=env)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "apt-get install" in proc.stderr


@pytest.mark.parametrize("args", [("--mem", "1X"), ("--mem", "9"), ("--timeout", "0")])
def test_the_launcher_refuses_bad_options_in_one_line(args):
    proc = launch(*args, "--", "true")
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: ")
