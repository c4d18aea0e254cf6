"""The supervisor's node processes: each started with its own log, awaited until READY (or
stuck), stopped by PID; the signals that stop a run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Optional


from hil.transport.bus import die_with_parent, terminate


EXIT_NODE = 1
EXIT_INTERRUPTED = 130
READY_IDLE_S = 30.0          # a starting node that uses no CPU for this long is stuck
READY_CAP_S = 900.0          # and none may take longer than this to start (cold caches, UML)


class NodeFailure(RuntimeError):
    pass


class Node:
    """A node process started by the supervisor (stdout: READY line; stderr: DIR/<name>.log)."""

    def __init__(self, name: str, argv: list[str], out: Path, env: Optional[dict] = None):
        self.name = name
        self.errlog = out / f"{name}.log"
        self._err = open(self.errlog, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hil", name, *argv], stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=self._err, start_new_session=True,
            preexec_fn=die_with_parent, env=env)
        self.ready = threading.Event()
        self.lines: deque = deque(maxlen=50)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            line = raw.decode(errors="replace").rstrip()
            if line == "READY":
                self.ready.set()
            else:
                self.lines.append(line)

    def wait_ready(self, idle_s: float = READY_IDLE_S, cap_s: float = READY_CAP_S) -> None:
        """Until the node prints READY. Starting means importing and loading (or, on a cold
        cache, compiling) the numba kernels, which takes from a second to minutes (three
        nodes compiling on UML's one CPU); so the wait is on progress, not a fixed time: the
        node fails when its CPU time stops advancing for ``idle_s`` (it is stuck, e.g. on a
        bus that never answers) or after ``cap_s`` in all."""
        start = time.monotonic()
        cpu, since = _cpu_time(self.proc.pid), start
        while not self.ready.wait(0.05):
            if self.proc.poll() is not None:
                raise NodeFailure(f"node {self.name} exited at start with code "
                                  f"{self.proc.returncode}: {self.last_error()}")
            now = time.monotonic()
            used = _cpu_time(self.proc.pid)
            if used > cpu:
                cpu, since = used, now
            if now - since > idle_s:
                raise NodeFailure(f"node {self.name} not ready: no progress (CPU time) for "
                                  f"{idle_s:g} s after {now - start:.0f} s")
            if now - start > cap_s:
                raise NodeFailure(f"node {self.name} not ready within {cap_s:g} s")

    def last_error(self) -> str:
        if not self._err.closed:
            self._err.flush()
        try:
            lines = [ln for ln in self.errlog.read_text(errors="replace").splitlines()
                     if ln.strip()]
        except OSError:
            lines = []
        return lines[-1] if lines else "(no message)"

    def terminate(self) -> None:
        terminate(self.proc)

    def stop(self, timeout_s: float = 10.0) -> Optional[int]:
        """SIGTERM, then SIGKILL after ``timeout_s``. Returns the exit code."""
        if self.proc.poll() is None:
            self.terminate()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._err.close()
        return self.proc.returncode


def _proc_stat(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command name (state first); [] if unreadable."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2:].split()
    except (OSError, ValueError):
        return []


def _cpu_time(pid: int) -> float:
    """User + system CPU seconds of a process, 0.0 when unreadable."""
    fields = _proc_stat(pid)
    try:
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (ValueError, IndexError):
        return 0.0


def stopped(pid: int) -> bool:
    """The process is stopped (SIGSTOP, a debugger): state T or t in /proc."""
    return _proc_stat(pid)[:1] in (["T"], ["t"])


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, SIGTERM or SIGHUP: the run stops the same way for each."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def on_signals():
    """SIGTERM and SIGHUP raise like Ctrl-C (once; a repeat during the cleanup is ignored).
    Returns the previous handlers."""
    fired = []

    def handler(signum, _frame):
        if not fired:
            fired.append(signum)
            raise Interrupted(signum)

    return {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGHUP)}
