"""The layers of docs/architecture.md as import-linter contracts (``pyproject.toml``; ``lint-imports``
is part of ``make test``): they hold on the tree, and an upward import breaks them."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")
PACKAGES = ("firmware", "calib", "hil", "tools")


def lint(cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(LINT), "--config", "pyproject.toml", "--no-cache"], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture
def tree(tmp_path):
    """The packages' Python files and pyproject.toml, copied."""
    for pkg in PACKAGES:
        for src in (ROOT / pkg).rglob("*.py"):
            dst = tmp_path / src.relative_to(ROOT)
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
    shutil.copyfile(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_the_contracts_hold_on_the_tree(tree):
    res = lint(tree)
    assert res.returncode == 0, res.stdout[-3000:]
    assert "0 broken" in res.stdout


@pytest.mark.parametrize("module, line", [
    ("firmware/modes.py", "import hil.sim.road\n"),            # firmware -> hil
    ("firmware/grade.py", "from calib import options\n"),   # firmware -> calib
    ("calib/options.py", "import hil.nodes.sil\n"),              # calib -> hil
    ("hil/sim/road.py", "from tools import analysis\n"),        # hil -> tools
    ("firmware/akf.py", "import scipy.linalg\n"),           # the firmware's purity
    ("calib/model.py", "import cantools\n"),                # calib reads no bus
    ("hil/sim/sensors.py", "import numba\n"),                   # numba only behind firmware.kernels
    ("firmware/util.py", "import firmware.fixedpoint\n"),  # a cycle: fixedpoint -> util
    # type-checking imports count too (a circle hidden behind them is still a circle)
    ("calib/model.py", "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import hil.config\n"),
    # hil's subpackages: each imports only those below it
    ("hil/sim/road.py", "import hil.nodes\n"),                # sim -> nodes
    ("hil/nodes/sil.py", "from hil.validate import campaign\n"),  # nodes -> validate
    ("hil/bench/procs.py", "from hil.validate import faults\n"),  # the runner -> the campaign
    ("hil/transport/codec.py", "from hil.sim import road\n"),   # transport | sim: independent
    ("hil/config.py", "import hil.kernels.road\n"),           # config is the floor
])
def test_an_upward_or_forbidden_import_breaks_a_contract(tree, module, line):
    path = tree / module
    path.write_text(path.read_text() + "\n" + line)
    res = lint(tree)
    assert res.returncode == 1, res.stdout[-3000:]
    assert "BROKEN" in res.stdout
