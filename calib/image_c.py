"""The memory image (``calib.image``) as C: packed structs that are the records byte for
byte, one object per segment in its own section, and a linker script that puts each at its
base address (``make tables`` writes ``c/generated/ecu_image.h``, ``ecu_image.c`` and
``ecu_image.ld``). Compiled and linked, their symbols are where the A2L says the objects
are: ``tests/test_a2l.py`` checks every address against what gcc lays out."""

from __future__ import annotations

import numpy as np

from calib.image import EPK_LEN, Image

HEADER, SOURCE, LINKER = "ecu_image.h", "ecu_image.c", "ecu_image.ld"
CTYPE = {"f8": "double", "i8": "int64_t", "i4": "int32_t", "u1": "uint8_t"}
# segment -> (C type, C symbol, section)
SYMBOLS = {"CAL": ("ecu_cal_t", "ecu_cal"), "FX": ("ecu_fx_t", "ecu_fx"),
           "STATE": ("ecu_state_t", "ecu_state"), "INPUTS": ("ecu_inputs_t", "ecu_inputs"),
           "OUTPUTS": ("ecu_outputs_t", "ecu_outputs")}


def _structs(dt: np.dtype, tname: str, out: list[str]) -> None:
    """Typedefs for ``dt`` (its nested records first), as ``tname``."""
    members = []
    for n in dt.names:
        f = dt.fields[n][0]
        if f.names:
            sub = f"{tname[:-2]}_{n}_t"
            _structs(f, sub, out)
            members.append(f"    {sub} {n};")
            continue
        base, shape = f.subdtype if f.subdtype is not None else (f, ())
        dims = "".join(f"[{d}]" for d in shape)
        members.append(f"    {CTYPE[base.str.lstrip('<|')]} {n}{dims};")
    out.append("typedef struct __attribute__((packed)) {\n" + "\n".join(members)
               + f"\n}} {tname};")


def _dtypes(image: Image) -> dict:
    return {"CAL": image.P.dtype, "FX": image.T.dtype, "STATE": image.S_dtype,
            "INPUTS": image.I_dtype, "OUTPUTS": image.O_dtype}


def generate(image: Image, top: str) -> dict[str, str]:
    h = [top, "#ifndef ECU_IMAGE_H", "#define ECU_IMAGE_H", "", "#include <stdint.h>", "",
         f'#define ECU_IMAGE_EPK "{image.epk}"', f"#define ECU_IMAGE_EPK_LEN {EPK_LEN}"]
    h += [f"#define ECU_IMAGE_{s.name}_ADDR 0x{s.base:X}u\n#define ECU_IMAGE_{s.name}_SIZE "
          f"{s.size}u" for s in image.segments]
    types: list[str] = []
    for seg, dt in _dtypes(image).items():
        _structs(dt, SYMBOLS[seg][0], types)
    h += [""] + types + [""]
    h += [f"extern {t} {sym};" for t, sym in SYMBOLS.values()]
    h += [f"extern const char ecu_epk[{EPK_LEN}];", "",
          "/* each record is its segment, byte for byte */"]
    h += [f"_Static_assert(sizeof({SYMBOLS[s.name][0]}) == {s.size}u, \"{s.name} size\");"
          for s in image.segments if s.name in SYMBOLS]
    h += ["", "#endif /* ECU_IMAGE_H */", ""]
    c = [top, f'#include "{HEADER}"', "",
         f'const char ecu_epk[{EPK_LEN}] __attribute__((section(".ecu_epk"), used)) = '
         "ECU_IMAGE_EPK;"]
    c += [f'{t} {sym} __attribute__((section(".{sym}"), used));'
          for t, sym in SYMBOLS.values()]
    ld = [top, "SECTIONS", "{"]
    for s in image.segments:
        sym = "ecu_epk" if s.name == "IDENT" else SYMBOLS[s.name][1]
        ld.append(f"  .{sym} 0x{s.base:X} : {{ KEEP(*(.{sym})) }}")
    ld += ["  /DISCARD/ : { *(.comment) *(.note*) }", "}", ""]
    return {HEADER: "\n".join(h), SOURCE: "\n".join(c) + "\n", LINKER: "\n".join(ld)}
