"""PID 1 inside User-mode Linux (``hil.transport.vcan``'s guest): mount the machine's file
systems, load the CAN modules, bring ``vcan0`` up, run the command with the host's
environment and working directory (``candump -L vcan0`` beside it when asked), write its exit
status for the host and power off: ``python -m hil.transport.vcan_guest SPEC.json`` (the init
the host writes)."""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

from hil.transport.vcan import CHANNEL, EXIT_LOST, GUEST_MARK


MOUNTS = (("proc", "/proc", "proc", ""), ("sysfs", "/sys", "sysfs", ""),
          ("devtmpfs", "/dev", "devtmpfs", ""), ("devpts", "/dev/pts", "devpts", ""),
          ("tmpfs", "/dev/shm", "tmpfs", "mode=1777"), ("tmpfs", "/run", "tmpfs", "mode=755"))


def _libc():
    return ctypes.CDLL(None, use_errno=True)


def _mount(src: str, target: str, fstype: str, opts: str) -> None:
    libc = _libc()
    os.makedirs(target, exist_ok=True)      # (/dev/pts, /dev/shm: on the fresh devtmpfs)
    if libc.mount(src.encode(), target.encode(), fstype.encode(), 0,
                  opts.encode() if opts else None) != 0:
        err = ctypes.get_errno()
        if err != 16:                       # EBUSY: devtmpfs may be mounted already
            raise OSError(err, f"mount {fstype} on {target}: {os.strerror(err)}")


def _insmod(path: str) -> None:
    libc = _libc()
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        if libc.syscall(313, fd, b"", 0) != 0:        # finit_module (x86_64)
            err = ctypes.get_errno()
            if err != 17:                              # EEXIST: built in or loaded
                raise OSError(err, f"insmod {path}: {os.strerror(err)}")
    finally:
        os.close(fd)


def _ip(*args: str) -> None:
    ip = shutil.which("ip") or "/sbin/ip"
    res = subprocess.run([ip, *args], capture_output=True, text=True)
    if res.returncode != 0:
        raise OSError(f"ip {' '.join(args)}: {res.stderr.strip()}")


def _raw_output(fd: int) -> None:
    """No output processing on a console tty (a '\\n' stays one byte, as on a pipe)."""
    import termios

    attrs = termios.tcgetattr(fd)
    attrs[1] &= ~termios.OPOST
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


def _can_receivers(channel: str = CHANNEL) -> int:
    try:
        return sum(1 for ln in Path("/proc/net/can/rcvlist_all").read_text().splitlines()
                   if ln.split()[:1] == [channel])
    except OSError:
        return 0


def start_candump(path, env: Optional[dict] = None,
                  channel: str = CHANNEL) -> subprocess.Popen:
    """``candump -L CHANNEL > path`` (can-utils), returned once its socket is on the
    channel's receive list (/proc/net/can/rcvlist_all), so no frame sent after this returns
    is missed. Stop it with :func:`stop_candump`."""
    before = _can_receivers(channel)
    with open(path, "wb") as f:
        rec = subprocess.Popen(["candump", "-L", channel], stdin=subprocess.DEVNULL, stdout=f,
                               stderr=subprocess.DEVNULL, env=env)
    deadline = time.monotonic() + 10
    while _can_receivers(channel) <= before:
        if rec.poll() is not None or time.monotonic() > deadline:
            stop_candump(rec)
            raise OSError(f"candump did not start listening on {channel}")
        time.sleep(0.01)
    return rec


def stop_candump(rec: subprocess.Popen) -> bool:
    """SIGINT (candump flushes its output and exits), SIGKILL after 10 s; False if killed."""
    if rec.poll() is not None:
        return True
    rec.send_signal(signal.SIGINT)
    try:
        rec.wait(10)
        return True
    except subprocess.TimeoutExpired:
        rec.kill()
        rec.wait(5)
        return False


def _relay(proc: subprocess.Popen, pipes: dict) -> None:
    """Copy the command's piped stdout/stderr to the consoles until both close (or the
    command has ended and its pipes stay quiet for a moment: a background child holds them)."""
    import select

    pipes = {r: w for r, w in pipes.items() if r is not None}
    quiet_since = None
    while pipes:
        ready = select.select(list(pipes), [], [], 0.2)[0]
        for r in ready:
            chunk = os.read(r.fileno(), 65536)
            if chunk:
                os.write(pipes[r], chunk)
            else:
                del pipes[r]
        if ready:
            quiet_since = None
        elif proc.poll() is not None:
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since > 1.0:
                break


def _power_off() -> None:
    os.sync()
    _libc().reboot(0x4321FEDC)             # LINUX_REBOOT_CMD_POWER_OFF
    os._exit(0)


def guest(spec_path: str) -> None:
    """PID 1 in UML: set up the machine and vcan0, run the command, write rc, power off."""
    spec = json.loads(Path(spec_path).read_text())
    result: dict = {"code": EXIT_LOST}
    try:
        for mount in MOUNTS:
            _mount(*mount)
        for ko in spec["modules"]:
            _insmod(ko)
        _ip("link", "set", "lo", "up")
        _ip("link", "add", "dev", CHANNEL, "type", "vcan")
        _ip("link", "set", "up", CHANNEL)
        tty_out = os.open("/dev/tty1", os.O_RDWR | os.O_NOCTTY)
        tty_err = os.open("/dev/tty2", os.O_WRONLY | os.O_NOCTTY)
        _raw_output(tty_err)
        interactive = spec["interactive"]
        if not interactive:
            _raw_output(tty_out)
        env = dict(spec["env"], **{GUEST_MARK: "1"})
        env.pop("LD_PRELOAD", None)
        try:
            os.chdir(spec["cwd"])
        except OSError:
            os.chdir("/")

        def child_setup():
            os.setsid()
            if interactive:
                import fcntl
                import termios

                fcntl.ioctl(0, termios.TIOCSCTTY, 0)

        recorder = start_candump(spec["candump"], env) if spec["candump"] else None
        stdin = tty_out if interactive else subprocess.DEVNULL
        out_tty, err_tty = (True, True) if interactive else spec["tty"]
        try:
            proc = subprocess.Popen(spec["argv"], stdin=stdin,
                                    stdout=tty_out if out_tty else subprocess.PIPE,
                                    stderr=(tty_out if interactive else tty_err) if err_tty
                                    else subprocess.PIPE,       # (a shell: one terminal)
                                    env=env, preexec_fn=child_setup)
            _relay(proc, {proc.stdout: tty_out, proc.stderr: tty_err})
            result = {"code": proc.wait()}
            if result["code"] < 0:
                result["code"] = 128 - result["code"]
        except OSError as exc:
            result = {"code": 127 if isinstance(exc, FileNotFoundError) else 126,
                      "error": f"cannot run {spec['argv'][0]!r}: {exc.strerror or exc}"}
        if recorder is not None and not stop_candump(recorder):
            result.setdefault("error", "candump did not stop on SIGINT; killed")
    except Exception as exc:  # noqa: BLE001 - told to the host, then power off
        result = {"code": EXIT_LOST, "error": f"setting up the UML guest failed: {exc}"}
    finally:
        try:
            tmp = spec["rc"] + ".tmp"
            Path(tmp).write_text(json.dumps(result))
            os.replace(tmp, spec["rc"])
        finally:
            _power_off()


if __name__ == "__main__":
    if len(sys.argv) != 2 or os.getpid() != 1:
        sys.exit("vcan_guest: runs only as PID 1 inside User-mode Linux (python -m hil vcan)")
    guest(sys.argv[1])
