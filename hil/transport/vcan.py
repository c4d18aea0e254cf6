"""``python -m hil vcan [-- COMMAND ...]``: a command (or a shell) in a real Linux kernel with
SocketCAN and ``vcan0`` up, on a host whose own kernel has no CAN.

The kernel is User-mode Linux (Debian's ``user-mode-linux``: ``linux.uml``, an ordinary program,
with its modules under ``/usr/lib/uml/modules/VERSION``). It boots with the host's root file
system mounted read-write through ``hostfs``, so the project, its ``.venv`` and can-utils run
inside unchanged. PID 1 is ``hil.transport.vcan_guest``: it mounts /proc, /sys, /dev, /dev/pts,
and tmpfs on /dev/shm and /run (the guest's own), brings ``lo`` up, loads ``can``,
``can-raw``, ``can-bcm``, ``can-dev`` and ``vcan`` (with the modules they depend on, from
``modules.dep``), creates ``vcan0``, runs the command with this process's environment and
working directory, writes its exit status for the host and powers the machine off. With
``--candump FILE``, ``candump -L vcan0`` records into FILE from before the command starts until
after it ends.

The command's stdout and stderr come back on this process's (through UML consoles 1 and 2;
each is a terminal in the guest only when it is one here); the kernel's own messages go to a
boot log, shown when something went wrong. The exit status is the command's; 124 when
``--timeout`` ran out, 130 on Ctrl-C (143 on SIGTERM, 129 on SIGHUP), 125 when UML ended
without one (the boot log's tail is printed), 2 when UML, its CAN modules or (for
``--candump``) can-utils are missing (one line with the command that installs them). UML runs
in its own process group; on every way out the whole group is ended by its ID (SIGTERM, then
SIGKILL), and UML gets SIGTERM should this process die, so nothing outlives the launcher;
nothing is mounted on the host. The run's files (a 0700 directory with the command, its
environment and the exit status) are removed at the end.

On hosts with AMX (a larger XSAVE area than UML's), UML 6.1 cannot restore its guests' FPU
state; ``hil/transport/uml_xstate.c`` (built here with gcc, cached) is preloaded into ``linux.uml`` to
fix that, and does nothing where it is not needed. UML has one CPU and a 100 Hz tick: it is for
functional tests of real SocketCAN, not for timing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

UML = "linux.uml"
UML_ENV = "HIL_UML"                     # another linux.uml to use (e.g. a newer build)
MODULES_ROOT = Path("/usr/lib/uml/modules")
CAN_MODULES = ("can", "can-raw", "can-bcm", "can-dev", "vcan")
CHANNEL = "vcan0"
INSTALL = "apt-get install -y user-mode-linux can-utils iproute2"
SHIM_SOURCE = Path(__file__).with_name("uml_xstate.c")
DEFAULT_TIMEOUT_S = 3600.0
DEFAULT_MEM = "2G"
STOP_GRACE_S = 3.0
EXIT_SETUP, EXIT_TIMEOUT, EXIT_LOST, EXIT_INTERRUPTED = 2, 124, 125, 130
GUEST_MARK = "HIL_VCAN_GUEST"           # set in the command's environment inside UML


class VcanError(RuntimeError):
    """UML cannot be started here; a one-line message with what to do."""


# -- host side ------------------------------------------------------------------------------

def find_uml() -> tuple[Path, str, list[Path]]:
    """(linux.uml, its kernel version, the CAN modules' .ko files in load order), or
    VcanError."""
    exe = os.environ.get(UML_ENV) or shutil.which(UML) or ""
    if not exe or not os.access(exe, os.X_OK):
        raise VcanError(f"User-mode Linux ({UML}) is not installed; as root: {INSTALL} "
                        f"(or `make vcan-setup`)")
    try:
        out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=20)
        version = out.stdout.strip().splitlines()[-1].strip()
    except (OSError, subprocess.SubprocessError, IndexError):
        raise VcanError(f"{exe} --version failed; is it a User-mode Linux kernel?") from None
    moddir = MODULES_ROOT / version
    deps = modules_dep(moddir)
    by_name = module_names(deps)
    missing = [m for m in CAN_MODULES if m not in by_name]
    if missing:
        raise VcanError(f"UML {version} has no module(s) {', '.join(missing)} under {moddir}; "
                        f"reinstall: {INSTALL}")
    return Path(exe), version, [moddir / rel for rel in load_order(deps, by_name)]


def modules_dep(moddir: Path) -> dict[str, list[str]]:
    """modules.dep: each module's path (relative to ``moddir``) -> the paths it depends on;
    empty when the file cannot be read."""
    try:
        lines = (moddir / "modules.dep").read_text().splitlines()
    except OSError:
        return {}
    deps = {}
    for line in lines:
        mod, sep, rest = line.partition(":")
        if sep and mod.strip():
            deps[mod.strip()] = rest.split()
    return deps


def module_names(deps: dict[str, list[str]]) -> dict[str, str]:
    """Module name (with '-' and '_' both) -> its path in ``deps``."""
    out = {}
    for rel in deps:
        name = Path(rel).name.split(".ko")[0]
        out[name] = out[name.replace("_", "-")] = rel
    return out


def load_order(deps: dict[str, list[str]], by_name: dict[str, str],
               names=CAN_MODULES) -> list[str]:
    """The module paths to insert for ``names``, dependencies first."""
    order: list[str] = []

    def visit(rel: str) -> None:
        for dep in deps.get(rel, []):
            visit(dep)
        if rel not in order:
            order.append(rel)

    for name in names:
        visit(by_name[name])
    return order


def shim_path() -> Optional[Path]:
    """The xstate shim, built once per source version (None without gcc: UML may then fail on
    hosts with AMX, and says so in its boot log)."""
    src = SHIM_SOURCE.read_bytes()
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "hil"
    lib = cache / f"uml_xstate-{hashlib.sha256(src).hexdigest()[:12]}.so"
    if lib.exists():
        return lib
    gcc = shutil.which("gcc") or shutil.which("cc")
    if gcc is None:
        return None
    cache.mkdir(parents=True, exist_ok=True)
    tmp = lib.with_suffix(f".{os.getpid()}.tmp")
    res = subprocess.run([gcc, "-O2", "-shared", "-fPIC", "-o", str(tmp), str(SHIM_SOURCE),
                          "-ldl"], capture_output=True, text=True)
    if res.returncode != 0:
        raise VcanError(f"building {SHIM_SOURCE.name} failed: {res.stderr.strip()[:300]}")
    tmp.replace(lib)
    return lib


def _run_dir() -> Path:
    """A private directory on the host's file system (which the guest sees): not on /dev/shm
    or /run, which the guest replaces."""
    base = Path(tempfile.gettempdir()).resolve()
    if base.is_relative_to("/dev/shm") or base.is_relative_to("/run"):
        base = Path("/var/tmp")
    return Path(tempfile.mkdtemp(prefix=f"hil-vcan-{os.getpid()}-", dir=base))


def mem_bytes(mem: str) -> int:
    """UML's ``mem=`` value (``512M``, ``2G``, bytes) in bytes; VcanError when it is not one."""
    text = mem.strip().upper()
    scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1:], 1)
    try:
        n = int(text[:-1] if scale > 1 else text) * scale
    except ValueError:
        n = 0
    if not (64 << 20 <= n <= 64 << 30):
        raise VcanError(f"--mem must be 64M to 64G, like 2G; got {mem!r}")
    return n


def _memory_dir(mem: str) -> str:
    """Where UML keeps its memory file (TMPDIR): /dev/shm when it has room for it (a file on
    a disk would make every guest page a disk page), else the temporary directory."""
    try:
        st = os.statvfs("/dev/shm")
        if os.access("/dev/shm", os.W_OK) and st.f_bavail * st.f_frsize > mem_bytes(mem):
            return "/dev/shm"
    except OSError:
        pass
    return tempfile.gettempdir()


def _boot_tail(path: Path, n: int = 12) -> str:
    try:
        lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "(no boot log)"
    return "\n".join(lines[-n:])


class _Signalled(KeyboardInterrupt):
    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _interrupt(signum, _frame):
    raise _Signalled(signum)


def _end_group(proc: subprocess.Popen) -> None:
    """Stop UML and everything it started: its process group, by ID (it is the group leader,
    started here with a new session), SIGTERM first, SIGKILL after the grace time."""
    pgid = proc.pid
    for sig, wait_s in ((signal.SIGTERM, STOP_GRACE_S), (signal.SIGKILL, STOP_GRACE_S)):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(wait_s)
        except subprocess.TimeoutExpired:
            continue
        # the leader is gone; its helpers (same group) may not be yet
        try:
            os.killpg(pgid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        break
    if proc.poll() is None:
        proc.wait(STOP_GRACE_S)


def run(command: list[str], timeout_s: float = DEFAULT_TIMEOUT_S, mem: str = DEFAULT_MEM,
        interactive: bool = False, quiet: bool = False, candump: Optional[str] = None) -> int:
    """Boot UML, run ``command`` in it with vcan0 up, return its exit status (see the module)."""
    from hil.transport.bus import die_with_parent

    mem_bytes(mem)
    exe, version, modules = find_uml()
    if candump is not None:
        if shutil.which("candump") is None:
            raise VcanError(f"--candump needs can-utils; as root: {INSTALL}")
        candump = str(Path(candump).resolve())
        Path(candump).parent.mkdir(parents=True, exist_ok=True)
    shim = shim_path()
    rundir = _run_dir()
    try:
        os.chmod(rundir, 0o700)
        init = _guest_files(rundir, command, modules, interactive, candump)
        boot = rundir / "boot.log"
        env = dict(os.environ)
        if shim is not None:
            env["LD_PRELOAD"] = str(shim)
        env["TMPDIR"] = _memory_dir(mem)
        stdin_fd = os.dup(0) if interactive else None
        out_fd, err_fd = os.dup(1), os.dup(2)
        cons_in = f"fd:{stdin_fd}" if stdin_fd is not None else "null"
        argv = [str(exe), f"mem={mem}", "root=/dev/root", "rootfstype=hostfs", "rootflags=/",
                "rw", f"init={init}", f"uml_dir={rundir}", f"umid=hil-{os.getpid()}",
                "con=null", "ssl=null", "con0=null,fd:1", f"con1={cons_in},fd:{out_fd}",
                f"con2=null,fd:{err_fd}"]
        if not quiet:
            print(f"vcan: booting User-mode Linux {version} ({exe}) with {CHANNEL}",
                  file=sys.stderr, flush=True)
        with open(boot, "wb") as log:
            proc = subprocess.Popen(
                argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env,
                pass_fds=[fd for fd in (stdin_fd, out_fd, err_fd) if fd is not None],
                start_new_session=True,
                preexec_fn=die_with_parent)     # (UML ends its own processes on SIGTERM)
        for fd in (stdin_fd, out_fd, err_fd):
            if fd is not None:
                os.close(fd)
        stopped = _wait(proc, timeout_s)
        if stopped is not None:
            return stopped
        try:
            rc = json.loads((rundir / "rc").read_text())
        except (OSError, ValueError):
            print(f"vcan: UML ended without the command's exit status; its boot log ends:\n"
                  f"{_boot_tail(boot)}", file=sys.stderr, flush=True)
            return EXIT_LOST
        if rc.get("error"):
            print(f"vcan: {rc['error']}", file=sys.stderr, flush=True)
        return int(rc["code"])
    finally:
        shutil.rmtree(rundir, ignore_errors=True)


def _guest_files(rundir: Path, command: list[str], modules: list[Path], interactive: bool,
                 candump: Optional[str]) -> Path:
    """The guest's specification (mode 0600: the command, this process's environment and
    directory) and its init, which runs ``hil.transport.vcan_guest`` as PID 1."""
    spec = {"argv": command, "cwd": os.getcwd(), "env": dict(os.environ),
            "modules": [str(p) for p in modules], "interactive": interactive,
            "tty": [os.isatty(1), os.isatty(2)], "candump": candump,
            "rc": str(rundir / "rc")}
    spec_path = rundir / "spec.json"
    fd = os.open(spec_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(spec, f)
    init = rundir / "init"
    init.write_text(f"#!/bin/sh\nexec {shlex.quote(sys.executable)} -m "
                    f"hil.transport.vcan_guest {shlex.quote(str(spec_path))}\n")
    init.chmod(0o700)
    return init


def _wait(proc: subprocess.Popen, timeout_s: float) -> Optional[int]:
    """Until UML ends by itself (None), or the timeout, Ctrl-C, SIGTERM or SIGHUP ends it (the
    exit status to return); either way its whole process group is ended."""
    deadline = time.monotonic() + timeout_s
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        while proc.poll() is None:
            if time.monotonic() > deadline:
                print(f"vcan: timeout: {timeout_s:g} s passed; UML stopped",
                      file=sys.stderr, flush=True)
                _end_group(proc)
                return EXIT_TIMEOUT
            time.sleep(0.1)
    except KeyboardInterrupt as exc:
        print(f"vcan: interrupted{f' ({exc})' if str(exc) else ''}; UML stopped",
              file=sys.stderr, flush=True)
        _end_group(proc)
        return 128 + exc.signum if isinstance(exc, _Signalled) else EXIT_INTERRUPTED
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    _end_group(proc)            # (helpers of a UML that ended by itself)
    return None


def main(argv: Optional[list[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(
        prog="python -m hil vcan", description=__doc__.split("\n\n")[0],
        epilog="e.g. python -m hil vcan -- candump -L vcan0   |   python -m hil vcan (a shell)")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                        help=f"wall-time limit (default {DEFAULT_TIMEOUT_S:g} s; exit 124)")
    parser.add_argument("--mem", default=DEFAULT_MEM, help="UML's memory (default 2G)")
    parser.add_argument("--quiet", action="store_true", help="no boot line")
    parser.add_argument("--candump", metavar="FILE",
                        help="record every frame on vcan0 with candump -L into FILE, from "
                             "before the command starts until after it ends")
    parser.add_argument("command", nargs=argparse.REMAINDER,
                        help="the command to run (default: an interactive shell)")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    interactive = not command
    if interactive:
        if not (sys.stdin.isatty() and sys.stdout.isatty()):
            print("error: no command given and no terminal for a shell", file=sys.stderr)
            return EXIT_SETUP
        command = [os.environ.get("SHELL") or "/bin/bash", "-i"]
    if not (args.timeout > 0):
        print("error: --timeout must be > 0", file=sys.stderr)
        return EXIT_SETUP
    if os.environ.get(GUEST_MARK):
        print("error: already inside the UML guest (vcan0 is up here)", file=sys.stderr)
        return EXIT_SETUP
    try:
        return run(command, args.timeout, args.mem, interactive, args.quiet, args.candump)
    except VcanError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_SETUP


if __name__ == "__main__":
    raise SystemExit(main())
