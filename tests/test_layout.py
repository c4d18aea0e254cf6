"""Layout rules of DESIGN.md §2: firmware/ stays pure."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"time", "random", "threading", "os", "socket", "subprocess", "can", "cantools",
             "hil", "asyncio", "multiprocessing", "datetime", "io", "pathlib", "sys", "scipy",
             "tools"}


def imported_roots(tree: ast.AST) -> set[str]:
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("__import__", "open", "exec", "eval"):
            roots.add(f"<call {node.func.id}>")
    return roots


def test_firmware_imports_no_io_clock_randomness():
    files = sorted((ROOT / "firmware").rglob("*.py"))
    assert files
    for path in files:
        bad = imported_roots(ast.parse(path.read_text(), str(path))) & (FORBIDDEN | {
            "<call __import__>", "<call open>", "<call exec>", "<call eval>"})
        assert not bad, f"{path}: {sorted(bad)}"


def test_the_scanner_catches_forbidden_imports():
    tree = ast.parse("import time\nfrom can import Bus\nimport numpy\nopen('x')\n")
    assert {"time", "can", "<call open>"} <= imported_roots(tree)


def test_openblas_kernels_are_pinned_in_the_test_processes():
    """hil.blas: on an AVX2 x86-64 host numpy's and scipy's OpenBLAS run the Haswell kernels
    (so an AVX-512 host computes the same calibration bytes), and one thread each, unless the
    environment chose."""
    import os

    import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS)

    from hil import blas

    threads = int(os.environ.get(blas.THREADS_VAR, "1"))
    assert blas.loaded_threads() == {"numpy": threads, "scipy": threads}
    core = blas.wanted_core()
    if core is None:
        return
    want = os.environ.get(blas.VAR, core)
    assert blas.loaded_cores() == {"numpy": want, "scipy": want}
