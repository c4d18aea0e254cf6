"""C-portable coefficient tables: everything the firmware needs, as a C99 header and source
(``generate``; the command line is ``python -m tools.tables``, ``make tables``).

Naming (CMSIS style): a quantity NAME is given as ``NAME_F32`` (float) and ``NAME_Q31`` (int32
mantissa) with ``NAME_Q31_FRAC`` fractional bits: NAME = NAME_Q31 * 2^-NAME_Q31_FRAC (Q0.31,
CMSIS q31, when the FRAC is 31; the bits are chosen per value for the most precision that fits,
and for the ``FX_`` constants of the fixed-point control path so that every product's shift is
in [0, 62]). Arrays have per-element ``_Q31_FRAC`` arrays and a ``_LEN``. Counts, ticks and
enumerations are plain integers. Rounding is half away from zero, values saturate.

Sections: ``ADC_``, ``PLANT_``, ``AKF_`` (the discretised model Phi, Gamma, H, D, Q per unit
road intensity, R0, P0, forgetting factor), ``GRADE_`` (classifier, thresholds, hysteresis),
``MODES_``, ``CONTROL_`` (LQR gains per mode, PID and BP-PID network weights and learning
constants, regen law, force limit), ``ACTUATOR_`` (current loop), ``FX_`` (the fixed-point
control path of ``firmware/fx`` and ``c/ecu_fx.c``: its signal formats ``FX_F_*``, the
constants in the formats it uses them, the tanh table). The header carries its generator and
the SHA-256 of its inputs (vehicle file, gains file, design options), never a date:
regenerating gives the same bytes.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
import numpy as np

from calib.ecu_params import GENERATOR, build, inputs_digest  # noqa: F401 (re-exported)
from calib.fx_tables import build_tables
from calib.options import DesignOptions
from calib.vehicle import VehicleConfig
from firmware import akf
from firmware.fixedpoint import INT32_MIN, best_frac, to_fixed
from firmware.kernels import akf as kern
from firmware.layout import params_record
from firmware.fx import tables as fixed
from firmware.params import CTRL_NAMES, MODE_NAMES, EcuParams


HEADER = "ecu_tables.h"
SOURCE = "ecu_tables.c"


def _f32(v: float) -> str:
    text = f"{float(np.float32(v)):.9g}"
    if not any(ch in text for ch in ".en"):
        text += ".0"
    return f"({text}f)" if text.startswith("-") else text + "f"


def _i32(v: int) -> str:
    return "(-2147483647 - 1)" if v == INT32_MIN else (f"({v})" if v < 0 else str(v))


def _auto_frac(v: float) -> int:
    return 31 if v == 0.0 else best_frac(v, 0, 62)


class Emitter:
    def __init__(self):
        self.h: list[str] = []
        self.c: list[str] = []
        self.names: set[str] = set()

    def _name(self, name: str) -> str:
        name = name.upper()
        if name in self.names:
            raise ValueError(f"duplicate table name {name}")
        self.names.add(name)
        return name

    def comment(self, text: str) -> None:
        self.h.append(f"\n/* {text} */")

    def integer(self, name: str, v: int) -> None:
        self.h.append(f"#define {self._name(name)} {_i32(int(v))}")

    def scalar(self, name: str, v: float, m: int | None = None, frac: int | None = None) -> None:
        name = self._name(name)
        if m is None:
            frac = _auto_frac(float(v))
            m = to_fixed(float(v), frac)
        self.h.append(f"#define {name}_F32 {_f32(v)}")
        self.h.append(f"#define {name}_Q31 ((int32_t){_i32(m)})")
        self.h.append(f"#define {name}_Q31_FRAC {frac}")

    def _array(self, ctype: str, name: str, items: list[str]) -> None:
        n = len(items)
        self.h.append(f"extern const {ctype} {name}[{n}];")
        rows = [", ".join(items[i:i + 6]) for i in range(0, n, 6)]
        self.c.append(f"const {ctype} {name}[{n}] = {{\n    " + ",\n    ".join(rows) + "\n};")

    def array(self, name: str, values, ms=None, fracs=None) -> None:
        name = self._name(name)
        values = [float(v) for v in np.asarray(values, dtype=float).ravel()]
        if ms is None:
            fracs = [_auto_frac(v) for v in values]
            ms = [to_fixed(v, f) for v, f in zip(values, fracs)]
        self.h.append(f"#define {name}_LEN {len(values)}")
        self._array("float", f"{name}_F32", [_f32(v) for v in values])
        self._array("int32_t", f"{name}_Q31", [_i32(m) for m in ms])
        self._array("int8_t", f"{name}_Q31_FRAC", [str(f) for f in fracs])

    def int_array(self, name: str, values, ctype: str = "int32_t") -> None:
        name = self._name(name)
        self.h.append(f"#define {name}_LEN {len(values)}")
        self._array(ctype, name, [_i32(int(v)) for v in values])


def _emit_params(e: Emitter, prefix: str, obj) -> None:
    """Every field of a parameter dataclass: floats and arrays as F32/Q31, ints as integers."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        name = f"{prefix}_{f.name}"
        if dataclasses.is_dataclass(v):
            _emit_params(e, name, v)
        elif isinstance(v, bool):
            e.integer(name, int(v))
        elif isinstance(v, int):
            e.integer(name, v)
        elif isinstance(v, float):
            e.scalar(name, v)
        elif isinstance(v, np.ndarray):
            e.array(name, v)
        elif isinstance(v, tuple) and all(isinstance(x, int) for x in v):
            e.int_array(name, v, "uint8_t")
        else:
            raise TypeError(f"{name}: cannot export {type(v).__name__}")


# The covariance side of the AKF as the ECU computes it (double; c/akf_cov.c), in the order
# of firmware.kernels.akf; ``*_var``: the variances of the forces off the model.
# (AKF_ADAPTIVE and AKF_BIAS_ADAPTIVE are the integers of the AKF section.)
AKF_F64 = ("phi", "gamma", "q_unit", "H", "r0", "r_floor", "r_scale", "p0", "forgetting",
           "gamma_wheel", "lift_force_var", "current_force_var", "stroke_force_var")


def _hex(v: float) -> str:
    if not math.isfinite(v):
        raise ValueError(f"cannot export the non-finite {v} as a C constant")
    return v.hex()


def _emit_akf_f64(e: Emitter, p: EcuParams) -> None:
    """The AKF's parameters bit for bit, as the ECU's record holds them: C99 hex floats in
    initialiser macros (``static const akf_real x[] = NAME_F64;``: a float32 build rounds
    them at compile time), row-major; scalars as plain constants; and the guard's."""
    rec = params_record(p)[0]["akf"]
    for name in AKF_F64:
        v = np.asarray(rec[name], dtype=float)
        full = e._name(f"akf_{name}_f64")
        if v.ndim == 0:
            e.h.append(f"#define {full} {_hex(float(v))}")
            continue
        e.h.append(f"#define {full}_LEN {v.size}")
        items = [_hex(float(x)) for x in v.ravel()]
        rows = [", ".join(items[i:i + 4]) for i in range(0, len(items), 4)]
        e.h.append(f"#define {full} {{ \\\n    " + ", \\\n    ".join(rows) + " }")
    e.h.append(f"#define {e._name('akf_r_ceiling_f64')} {_hex(kern.R_CEILING)}")
    e.integer("akf_jacobi_sweeps", kern.JACOBI_SWEEPS)
    e.h.append(f"#define {e._name('akf_skip_scale_f64')} {_hex(akf.SKIP_SCALE)}")
    for name in ("COV_ADAPT", "COV_LIFTED", "COV_CURRENT_UNKNOWN", "COV_STROKE_UNKNOWN",
                 "COV_RESTART"):
        e.integer(f"AKF_{name}", getattr(akf, name))


def _emit_fx(e: Emitter, T: fixed.FxTables) -> None:
    for f in ("F_ACC", "F_VEL", "F_POS", "F_FORCE", "F_CUR", "F_VOLT", "F_JERK", "F_NN", "F_W",
              "F_TANH", "TANH_STEP_BITS", "TANH_N", "GAIN_HEADROOM_BITS"):
        e.integer(f"FX_{f}", getattr(fixed, f))
    e.int_array("FX_STATE_FRAC", fixed.STATE_FRAC, "int8_t")
    e.int_array("FX_MEAS_FRAC", fixed.MEAS_FRAC, "int8_t")
    e.int_array("FX_ADC_FRAC", fixed.ADC_FRAC, "int8_t")
    for f in dataclasses.fields(T):
        v = getattr(T, f.name)
        name = f"FX_{f.name}"
        if isinstance(v, fixed.Fx):
            e.scalar(name, v.value, v.m, v.frac)
        elif isinstance(v, bool):
            e.integer(name, int(v))
        elif isinstance(v, int):
            e.integer(name, v)
        elif f.name == "tanh_lut":
            e.int_array("FX_TANH_LUT_Q31", v)
        elif f.name == "k_frac":
            e.int_array("FX_K_Q31_FRAC", v, "int8_t")
        elif f.name == "controllers":
            e.int_array("FX_CONTROLLERS", v, "uint8_t")
        elif isinstance(v, tuple) and all(isinstance(x, fixed.Fx) for x in v):
            e.array(name, [x.value for x in v], [x.m for x in v], [x.frac for x in v])
        else:
            raise TypeError(f"{name}: cannot export {type(v).__name__}")


def generate(cfg: VehicleConfig, gains_file: Path | None = None,
             opts: DesignOptions | None = None, params: EcuParams | None = None) -> dict[str, str]:
    """{file name: text} of the tables."""
    opts = opts or DesignOptions()
    p = params or build(cfg, opts, gains_file)
    digest = inputs_digest(cfg, gains_file, opts)
    e = Emitter()
    e.comment("enumerations (firmware.params)")
    for i, n in enumerate(MODE_NAMES):
        e.integer(f"MODE_{n}", i)
    for i, n in enumerate(CTRL_NAMES):
        e.integer(f"CTRL_{n}", i)
    e.comment("ECU tick")
    e.scalar("ECU_DT_S", p.dt_s)
    for f in dataclasses.fields(p):
        v = getattr(p, f.name)
        if dataclasses.is_dataclass(v):
            e.comment(f"{f.name} (firmware.params.{type(v).__name__})")
            _emit_params(e, f.name, v)
    e.comment("AKF road intensity")
    e.integer("AKF_Q_FOLLOWS_GRADE", int(p.akf_q_follows_grade))
    e.scalar("AKF_Q_GQ_NOMINAL", p.akf_q_gq_nominal)
    e.comment("AKF covariance side in double, bit for bit (firmware.kernels.akf, c/akf_cov.c)")
    _emit_akf_f64(e, p)
    e.comment("fixed-point control path (firmware/fx, c/ecu_fx.c)")
    _emit_fx(e, build_tables(p))
    top = (f"/* Generated by {GENERATOR}: do not edit.\n"
           f" * Inputs SHA-256: {digest}\n"
           f" * Vehicle: {Path(cfg.source).name}\n"
           " * NAME_F32: float; NAME_Q31: int32 mantissa; NAME_Q31_FRAC: its fractional bits,\n"
           " * NAME = NAME_Q31 * 2^-NAME_Q31_FRAC. See calib/c_tables.py and docs/ecu.md. */\n")
    guard = "ECU_TABLES_H"
    header = (top + f"#ifndef {guard}\n#define {guard}\n\n#include <stdint.h>\n\n"
              f'#define ECU_TABLES_INPUTS_SHA256 "{digest}"\n' + "\n".join(e.h)
              + f"\n\n#endif /* {guard} */\n")
    source = top + f'\n#include "{HEADER}"\n\n' + "\n\n".join(e.c) + "\n"
    return {HEADER: header, SOURCE: source}
