"""Layout rules of docs/architecture.md (Layers) beyond the import-linter contracts (tests/test_layers.py): the
firmware imports only what a pure fixed-step ECU needs (an allow-list, so a new dependency
cannot slip in), and the test processes run with OpenBLAS's kernels pinned."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what firmware/ may import: the language, numpy, and numba behind firmware.kernels only (with
# llvmlite, numba's code generator, that makes a shared library's symbols visible to it)
ALLOWED = {"__future__", "math", "dataclasses", "typing", "numpy", "firmware"}
ALLOWED_IN = {"firmware/kernels/__init__.py": {"numba", "llvmlite"}}
CALLS = ("__import__", "open", "exec", "eval", "compile", "input")


def imported_roots(tree: ast.AST) -> set[str]:
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            roots.add(node.module.split(".")[0] if node.level == 0 and node.module
                      else f"<relative {node.module}>")
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) in CALLS:
            roots.add(f"<call {node.func.id}>")
    return roots


def test_firmware_imports_only_what_the_allow_list_names():
    files = sorted((ROOT / "firmware").rglob("*.py"))
    assert len(files) > 20
    for path in files:
        rel = path.relative_to(ROOT).as_posix()
        bad = imported_roots(ast.parse(path.read_text(), rel)) - ALLOWED - ALLOWED_IN.get(rel, set())
        assert not bad, f"{rel}: {sorted(bad)}"


def test_the_scanner_sees_imports_and_calls():
    tree = ast.parse("import time\nfrom can import Bus\nimport numpy\nopen('x')\nfrom . import y\n")
    assert imported_roots(tree) - ALLOWED == {"time", "can", "<call open>", "<relative None>"}


def test_openblas_kernels_are_pinned_in_the_test_processes():
    """calib.blas: on an AVX2 x86-64 host numpy's and scipy's OpenBLAS run the Haswell kernels
    (so an AVX-512 host computes the same calibration bytes), and one thread each, unless the
    environment chose."""
    import os

    import scipy.linalg  # noqa: F401  (loads scipy's own OpenBLAS)

    from calib import blas

    threads = int(os.environ.get(blas.THREADS_VAR, "1"))
    assert blas.loaded_threads() == {"numpy": threads, "scipy": threads}
    core = blas.wanted_core()
    if core is None:
        pytest.skip("not an x86-64 host with AVX2 and FMA: no kernel pin (calib.blas)")
    want = os.environ.get(blas.VAR, core)
    assert blas.loaded_cores() == {"numpy": want, "scipy": want}


def function_lengths(path: Path) -> dict[str, int]:
    tree = ast.parse(path.read_text())
    return {node.name: node.end_lineno - node.lineno + 1 for node in ast.walk(tree)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))}


def test_firmware_functions_stay_short_and_the_tick_reads_in_one_screen():
    """No function in firmware/ (kernels included) over 80 lines; the tick (``ecu.tick``:
    the stages called in order, the fixed-point branches inline) at most 50."""
    long = {f"{path.relative_to(ROOT)}:{name}": n
            for path in sorted((ROOT / "firmware").rglob("*.py"))
            for name, n in function_lengths(path).items() if n > 80}
    assert not long, long
    assert function_lengths(ROOT / "firmware" / "ecu.py")["tick"] <= 50
    ecu_text = (ROOT / "firmware" / "ecu.py").read_text()
    assert "fx_tables" not in ecu_text                       # (tables come in built)


PACKAGES = ("firmware", "calib", "hil", "tools")
MAX_FILE_LINES = 500
MAX_FUNCTION_LINES = 80     # outside kernels/ (compiled code keeps a stage in one function)
HIL_TOP_MODULES = {"__init__.py", "__main__.py", "cli.py", "config.py", "hub.py", "parsers.py"}


def test_no_file_over_500_lines_and_no_function_over_80_outside_the_kernels():
    """A file holds one concept and a function reads in a screen or two (docs/architecture.md);
    the compiled kernels are exempt from the function rule only."""
    files = [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))]
    assert len(files) > 100
    big = {str(p.relative_to(ROOT)): n for p in files
           if (n := len(p.read_text().splitlines())) > MAX_FILE_LINES}
    assert not big, big
    long = {f"{p.relative_to(ROOT)}:{name}": n for p in files if "kernels" not in p.parts
            for name, n in function_lengths(p).items() if n > MAX_FUNCTION_LINES}
    assert not long, long


def test_hil_holds_subpackages_and_at_most_four_modules_at_its_top():
    top = {p.name for p in (ROOT / "hil").glob("*.py")}
    assert top == HIL_TOP_MODULES, top            # __main__, cli and at most 4 more
    assert len(top - {"__init__.py", "__main__.py", "cli.py"}) <= 4
    subs = {p.name for p in (ROOT / "hil").iterdir() if (p / "__init__.py").is_file()}
    assert subs == {"apps", "bench", "faults", "kernels", "nodes", "report", "sim", "transport",
                    "validate", "xcp"}, subs
