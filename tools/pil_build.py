"""The PIL images (``make pil``, ``tools.pil``): ``c/ecu_fx.c``, the generated tables and the
harness ``c/pil/`` cross-compiled with Debian's ``gcc-arm-none-eabi`` and picolibc for two
MPS2 boards QEMU models, run on ``qemu-system-arm`` with a deterministic virtual clock; the
ECU objects' flash and RAM (``arm-none-eabi-size``) and their worst-case stack over the call
graph (gcc's ``-fstack-usage`` and ``-fcallgraph-info=su``)."""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from tools.c_build import C_DIR, GEN

PIL_DIR = C_DIR / "pil"
# the host's flags (tools.c_build.CFLAGS) and no contraction of a*b+c into an FMA: the
# double-precision arithmetic must round as the host's does
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-ffp-contract=off",
          "-mthumb")
# -icount shift=7: 128 virtual ns per instruction, so the boards' 25 MHz SysTick (40 ns a
# count) resolves single instructions (c/pil/harness.c)
ICOUNT_SHIFT = 7
NS_PER_COUNT = 40
PACKAGES = "gcc-arm-none-eabi picolibc-arm-none-eabi qemu-system-arm"


@dataclass(frozen=True)
class Target:
    name: str
    machine: str          # qemu-system-arm -M
    flags: tuple
    what: str


TARGETS = {
    "m4f": Target("m4f", "mps2-an386",
                  ("-mcpu=cortex-m4", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"),
                  "Cortex-M4F (single-precision FPU), MPS2 AN386"),
    "m7": Target("m7", "mps2-an500", ("-mcpu=cortex-m7", "-mfpu=fpv5-d16", "-mfloat-abi=hard"),
                 "Cortex-M7 (double-precision FPU), MPS2 AN500"),
}
ECU_SOURCES = ("ecu_fx.c", "ecu_tables.c")
COV_SOURCES = ECU_SOURCES + ("akf_cov.c",)
# the estimator's build (c/akf_cov.h): double on the M7, float32 on the M4F (its FPU is
# single precision: a double would be a software routine); -fno-math-errno lets sqrt be the
# FPU's instruction (no errno to set; the same values)
COV_FLAGS = {"m4f": ("-DPIL_COV", "-DAKF_FLOAT", "-Wdouble-promotion", "-fno-math-errno"),
             "m7": ("-DPIL_COV", "-fno-math-errno")}


class PilError(RuntimeError):
    pass


def tool(name: str) -> str:
    path = shutil.which(name)
    if not path:
        raise PilError(f"{name} is needed for make pil (Debian, as root: apt-get install -y "
                       f"{PACKAGES})")
    return path


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    res = subprocess.run(cmd, capture_output=True, text=True, **kw)
    if res.returncode != 0 or res.stderr.strip():
        raise PilError(f"{' '.join(map(str, cmd))}\n{res.stderr}")
    return res


def build(target: Target, out: Path, gen: Path = GEN, cov: bool = False) -> Path:
    """The image for ``target`` in ``out`` (objects, .su and .ci files beside it); returns
    the ELF's path. ``cov``: with the covariance side of the filter in C (``COV_FLAGS``). A
    warning is an error."""
    cc = tool("arm-none-eabi-gcc")
    out.mkdir(parents=True, exist_ok=True)
    base = [cc, "--specs=picolibc.specs", *target.flags, *CFLAGS, f"-I{gen}", f"-I{C_DIR}",
            f"-I{PIL_DIR}", *(COV_FLAGS[target.name] if cov else ())]
    sources = {"ecu_fx.c": C_DIR / "ecu_fx.c", "ecu_tables.c": gen / "ecu_tables.c",
               "harness.c": PIL_DIR / "harness.c", "startup.c": PIL_DIR / "startup.c"}
    if cov:
        sources["akf_cov.c"] = C_DIR / "akf_cov.c"
    ecu = COV_SOURCES if cov else ECU_SOURCES
    objs = []
    for name, src in sources.items():
        obj = out / (Path(name).stem + ".o")
        extra = ["-fstack-usage", "-fcallgraph-info=su"] if name in ecu else []
        _run([*base, *extra, "-c", str(src), "-o", str(obj)], cwd=out)
        objs.append(obj)
    elf = out / "pil.elf"
    _run([*base, "-nostartfiles", "-T", str(PIL_DIR / "pil.ld"), *map(str, objs), "-o",
          str(elf), "-lm"])
    return elf


def soft_double_calls(obj: Path) -> list:
    """The software double-precision routines (``__aeabi_d*``) an object calls."""
    res = _run([tool("arm-none-eabi-nm"), "-u", str(obj)])
    return sorted({ln.split()[-1] for ln in res.stdout.splitlines()
                   if ln.split() and ln.split()[-1].startswith("__aeabi_d")})


def qemu_command(target: Target, elf: Path) -> list:
    return [tool("qemu-system-arm"), "-M", target.machine, "-nographic", "-monitor", "none",
            "-serial", "none", "-icount", f"shift={ICOUNT_SHIFT}", "-semihosting-config",
            "enable=on,target=native", "-kernel", str(elf)]


def instructions(counts: int) -> int:
    """A SysTick interval in instructions (exact: a count is 40/128 of one)."""
    return round(counts * NS_PER_COUNT / 2 ** ICOUNT_SHIFT)


def sizes(out: Path, sources=ECU_SOURCES) -> dict:
    """Flash (text + data) and static RAM (data + bss) of the ECU's objects, in bytes."""
    res = _run([tool("arm-none-eabi-size"), "-B",
                *(str(out / (Path(n).stem + ".o")) for n in sources)])
    text = data = bss = 0
    for line in res.stdout.splitlines()[1:]:
        t, d, b = (int(v) for v in line.split()[:3])
        text, data, bss = text + t, data + d, bss + b
    return {"text": text, "data": data, "bss": bss, "flash": text + data, "static_ram": data + bss}


_NODE = re.compile(r'node: \{ title: "([^"]+)" label: "([^"]*)"')
_EDGE = re.compile(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"')
_STACK = re.compile(r"(\d+) bytes \((static|dynamic|bounded)")


def worst_stack(out: Path, root: str = "fx_tick", sources=ECU_SOURCES) -> dict:
    """The deepest stack from ``root`` over the call graph of the ECU's objects (gcc's .ci
    files): the sum of the frames along the worst path. A call out of the graph (a library
    function) or a recursion is named: either makes the figure a lower bound."""
    frames, calls, kinds = {}, {}, {}
    for name in sources:
        text = (out / (Path(name).stem + ".ci")).read_text()
        for title, label in _NODE.findall(text):
            key = title.split(":")[-1]
            m = _STACK.search(label)
            if m:
                frames[key], kinds[key] = int(m.group(1)), m.group(2)
        for src, dst in _EDGE.findall(text):
            calls.setdefault(src.split(":")[-1], set()).add(dst.split(":")[-1])
    unknown, dynamic = set(), sorted(k for k, v in kinds.items() if v != "static")

    def depth(fn, path):
        if fn in path:
            raise PilError(f"recursion through {fn}: no stack bound")
        if fn not in frames:
            unknown.add(fn)
            return 0, [fn]
        best, via = 0, []
        for callee in sorted(calls.get(fn, ())):
            d, p = depth(callee, path | {fn})
            if d > best:
                best, via = d, p
        return frames[fn] + best, [fn, *via]

    total, path = depth(root, frozenset())
    return {"bytes": total, "path": path, "outside_the_graph": sorted(unknown),
            "not_static": dynamic}
