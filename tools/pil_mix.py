"""The executed instruction mix of the ECU's code on the M4F and the cycles per instruction it
implies (``tools.pil``; docs/pil.md): QEMU logs each translated block's instructions and each
block it executes (``-d in_asm,exec,nochain``, filtered to the ECU's code); every executed
instruction is classed by its mnemonic and costed with the Cortex-M4's cycle counts (its
Technical Reference Manual, "Processor instruction timings"), pessimistically where the manual
gives a range (every load and store 2 cycles, a division 12, a taken branch 1 + 3), with code
and constants in zero-wait-state memory. A conditional branch is taken when the next block
executed is not the one after it."""

from __future__ import annotations

import re
import subprocess
from collections import Counter
from pathlib import Path

from tools import pil_build as pb

REFILL = 3        # P, the pipeline refill of a taken branch: 1 to 3 cycles
_INS = re.compile(r"^0x([0-9a-f]+):\s+([0-9a-f]{4}(?: [0-9a-f]{4})?)\s+(\S+)\s*(.*)$")
_EXEC = re.compile(r"^Trace \d+: 0x[0-9a-f]+ \[[0-9a-f]+/([0-9a-f]+)/")
_COND = ("eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt",
         "gt", "le")


def _regs(ops: str) -> int:
    m = re.search(r"\{([^}]*)\}", ops)
    return len(m.group(1).split(",")) if m else 1


def classify(mn: str, ops: str) -> tuple:
    """(class, cycles if not a taken branch) of one Thumb-2 instruction."""
    base = mn.split(".")[0]
    if base in ("push", "pop", "ldm", "stm", "ldmia", "stmia", "ldmdb", "stmdb", "vpush",
                "vpop", "vldmia", "vstmia"):
        return "load/store multiple", 1 + _regs(ops)
    if base in ("ldrd", "strd"):
        return "load/store", 3
    if base.startswith(("ldr", "str", "vldr", "vstr")):
        return "load/store", 2
    if base in ("sdiv", "udiv"):
        return "divide", 12
    if base in ("vdiv", "vsqrt") or base.startswith(("vdiv", "vsqrt")):
        return "float divide/sqrt", 14
    if base.startswith("v"):
        return "float", 1
    if base in ("smull", "umull", "smlal", "umlal", "mul", "muls", "mla", "mls", "smmul",
                "smlabb", "smulbb"):
        return "multiply", 1
    if base in ("b", "bl", "bx", "blx", "cbz", "cbnz") or (
            base.startswith("b") and base[1:] in _COND):
        return "branch", 1
    return "alu", 1


def parse(log: Path) -> tuple:
    """(executed instructions by class, cycles) over the log."""
    blocks, block, mix, cycles = {}, None, Counter(), 0
    ends = None            # (address, size) of the branch that ended the last block run
    for line in log.read_text(errors="replace").splitlines():
        m = _INS.match(line)
        if m:
            addr = int(m.group(1), 16)
            if block is None:
                block = blocks[addr] = []
            block.append((addr, len(m.group(2).replace(" ", "")) // 2, m.group(3),
                          m.group(4)))
            continue
        block = None
        e = _EXEC.match(line)
        if not e:
            continue
        pc = int(e.group(1), 16)
        if ends is not None and pc != ends[0] + ends[1]:
            cycles += REFILL                     # the branch was taken
        ends = None
        for addr, size, mn, ops in blocks.get(pc, ()):
            cls, c = classify(mn, ops)
            mix[cls] += 1
            cycles += c
            if cls == "branch" or (mn.startswith(("pop", "ldm")) and "pc" in ops):
                ends = (addr, size)
    return mix, cycles


def measure(target: pb.Target, elf: Path, trace, work: Path, code: tuple) -> dict:
    """Run ``elf`` over ``trace`` (rows of trace.bin) logging the blocks in the address range
    ``code`` = (first, end); the mix and the CPI it implies."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "trace.bin").write_bytes(trace.tobytes())
    cmd = [*pb.qemu_command(target, elf), "-d", "in_asm,exec,nochain", "-dfilter",
           f"0x{code[0]:x}..0x{code[1] - 1:x}", "-D", "qemu.log"]
    res = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=600)
    if res.returncode != 0:
        raise pb.PilError(f"{target.name}: the logged run exited with {res.returncode}")
    mix, cycles = parse(work / "qemu.log")
    n = sum(mix.values())
    if n == 0:
        raise pb.PilError(f"{target.name}: QEMU logged no instruction of the ECU's code")
    return {"instructions": n, "cycles": cycles, "cpi": cycles / n,
            "mix": {k: v / n for k, v in sorted(mix.items(), key=lambda kv: -kv[1])}}


def code_range(elf: Path, first: str, end: str) -> tuple:
    """The addresses of two symbols of ``elf`` (the ECU's code lies from ``first`` to
    ``end``: pil.ld keeps the objects in link order)."""
    res = subprocess.run([pb.tool("arm-none-eabi-nm"), str(elf)], capture_output=True,
                         text=True, check=True)
    syms = {w[2]: int(w[0], 16) for w in (line.split() for line in res.stdout.splitlines())
            if len(w) == 3}
    return syms[first], syms[end]
