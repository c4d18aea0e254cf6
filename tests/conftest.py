"""Imported before any test module: ``hil`` pins OpenBLAS's kernels before numpy loads.

The SocketCAN tests (``tests/test_vcan.py``, marker ``needs_vcan``) need a kernel with CAN and
vcan0 up: they run in User-mode Linux (``make vcan-test``) or on a Linux host with vcan. The
launcher's own tests (marker ``needs_uml``) need UML on the host. Where either is missing
they are deselected, and the run says so in one line at the end."""

import functools
import os

import hil  # noqa: F401
from hil.transport.bus import kernel_has_vcan


@functools.lru_cache(maxsize=None)
def _absent() -> dict:
    from hil.transport import vcan

    uml = not os.environ.get(vcan.GUEST_MARK)            # (no UML inside UML)
    if uml:
        try:
            vcan.find_uml()
        except vcan.VcanError:
            uml = False
    return {"needs_vcan": not kernel_has_vcan(), "needs_uml": not uml}


def pytest_collection_modifyitems(config, items):
    absent = _absent()
    drop = [it for it in items if any(absent[m] and it.get_closest_marker(m) for m in absent)]
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = [it for it in items if it not in drop]


def pytest_terminal_summary(terminalreporter, config):
    absent = _absent()
    if hasattr(config, "workerinput") or not absent["needs_vcan"]:
        return
    terminalreporter.write_line(
        "vcan: the SocketCAN tests (tests/test_vcan.py) were not run: this kernel has no "
        "vcan0; `make vcan-test` runs them in User-mode Linux"
        + (" (install it as root: `make vcan-setup`)" if absent["needs_uml"] else ""))
