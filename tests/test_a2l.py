"""The ECU's A2L and memory image (calib.image, calib.a2l, calib.image_c): pya2ldb parses the
generated file; every object lies inside its segment and none overlap; every conversion is
its fixed-point format; every address is where gcc lays the object out in the image's C."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from calib import a2l, image_c
from calib.image import DATATYPE, Image, field
from firmware.ecu import Ecu, Inputs
from calib.fx_tables import build_tables
from hil.config import default_vehicle
from calib.ecu_params import build

ROOT = Path(__file__).resolve().parents[1]
GENERATED = ROOT / "c" / "generated"
IMAGE = Image(build(default_vehicle()))        # (what make tables generates)


@pytest.fixture(scope="module")
def parsed(tmp_path_factory):
    """The shipped A2L as pya2ldb reads it: {kind: {name: row}} and the module's MOD_PAR."""
    import pya2l
    import pya2l.model as model

    work = tmp_path_factory.mktemp("a2l")
    shutil.copy(GENERATED / a2l.A2L, work / a2l.A2L)
    s = pya2l.import_a2l(str(work / a2l.A2L), in_memory=True, loglevel="ERROR",
                         progress_bar=False)
    return {"MEASUREMENT": {m.name: m for m in s.query(model.Measurement).all()},
            "CHARACTERISTIC": {c.name: c for c in s.query(model.Characteristic).all()},
            "AXIS_PTS": {a.name: a for a in s.query(model.AxisPts).all()},
            "COMPU_METHOD": {c.name: c for c in s.query(model.CompuMethod).all()},
            "MOD_PAR": s.query(model.ModPar).first(),
            "SEGMENT": {m.name: m for m in s.query(model.MemorySegment).all()},
            "session": s}          # (kept open: the rows load their parts lazily)


def _address(row) -> int:
    return row.ecu_address.address if hasattr(row, "ecu_address") else row.address


def test_the_shipped_a2l_is_this_image_and_pya2ldb_reads_every_object(parsed):
    """The A2L in c/generated is the image of the default calibration (make tables-check
    says it is current); every object, its address and its type read back."""
    names = {**parsed["MEASUREMENT"], **parsed["CHARACTERISTIC"], **parsed["AXIS_PTS"]}
    assert set(names) == set(IMAGE.objects)
    assert parsed["MOD_PAR"].epk.identifier == IMAGE.epk
    assert parsed["MOD_PAR"].addr_epk[0].address == IMAGE.segment("IDENT").base
    for name, o in IMAGE.objects.items():
        row = names[name]
        assert _address(row) == o.address, name
        if name in parsed["MEASUREMENT"]:
            assert row.datatype == DATATYPE[o.dtype]
            assert (list(row.matrix_dim.numbers) if row.matrix_dim else []) == list(o.shape)
        lo, hi = row.lowerLimit, row.upperLimit
        assert lo <= hi, name
        if o.characteristic:        # the data stored lies within the A2L's limits
            raw = np.asarray(field(IMAGE.P if o.segment == "CAL" else IMAGE.T, o.path),
                             dtype=float).ravel()
            raw = raw if o.index is None else raw[o.index:o.index + 1]
            phys = raw * (2.0 ** -o.frac if o.frac is not None else 1.0)
            assert lo <= phys.min() and phys.max() <= hi, (name, lo, hi, phys)
    assert sum(o.writable for o in IMAGE.objects.values()) == sum(
        1 for c in parsed["CHARACTERISTIC"].values() if not c.read_only)


def test_every_object_lies_inside_its_segment_and_none_overlap(parsed):
    segs = parsed["SEGMENT"]
    assert {s.name for s in IMAGE.segments} == set(segs)
    spans = sorted((o.address, o.address + o.size, o.name) for o in IMAGE.objects.values())
    for start, end, name in spans:
        o = IMAGE.objects[name]
        s = segs[o.segment]
        assert s.address <= start and end <= s.address + s.size, name
    for (_, end, a), (start, _, b) in zip(spans, spans[1:]):
        assert end <= start, (a, b)
    ranges = sorted((s.address, s.address + s.size) for s in segs.values())
    for (_, end), (start, _) in zip(ranges, ranges[1:]):
        assert end <= start


def test_every_conversion_is_its_fixed_point_format(parsed):
    """FX: the factor is 2^-frac of the table's own frac field; the fixed-point state: the
    factor turns the integer into the float the same tick computed (a run of the fixed
    path, whose float mirror holds the same quantities), so a wrong format cannot pass."""
    cms = parsed["COMPU_METHOD"]
    rows = {**parsed["MEASUREMENT"], **parsed["CHARACTERISTIC"], **parsed["AXIS_PTS"]}

    def factor(name):
        conv = rows[name].conversion
        return 1.0 if conv == "NO_COMPU_METHOD" else cms[conv].coeffs_linear.a

    n_fx = 0
    for name, o in IMAGE.objects.items():
        if o.segment == "FX" and o.path[-1] == "m":
            frac = np.asarray(field(IMAGE.T, o.path[:-1] + ("frac",))).ravel()
            assert factor(name) == 2.0 ** -int(frac[o.index or 0]), name
            n_fx += 1
    assert n_fx > 100
    p = IMAGE.params
    e = Ecu(p, build_tables(p))
    rng = np.random.default_rng(1)
    for k in range(300):
        c = 2048 + (200 * np.sin(k / 20) * np.array([1, 1, 1, 0.2])
                    + rng.normal(0, 20, 4)).astype(int)
        e.step(Inputs(tick=k, body_accel=int(c[0]), wheel_accel=int(c[1]),
                      susp_defl=int(c[2]), motor_current=int(c[3]), speed=2000))
    S = e.S[0]
    mirror = {"ecu.fx.x": S["akf"]["x"], "ecu.fx.ba": S["adc"]["value"][0],
              "ecu.fx.wa": S["adc"]["value"][1], "ecu.fx.defl": S["adc"]["value"][2],
              "ecu.fx.cur": S["adc"]["value"][3], "ecu.fx.w_h": S["ctl"]["bppid"]["w_h"]}
    for base, want in mirror.items():
        want = np.atleast_1d(want).ravel()
        objs = [o for o in IMAGE.objects.values() if o.name.split("[")[0] == base]
        assert objs, base
        for o in objs:
            raw = np.asarray(field(e.S, o.path)).ravel()
            raw = raw if o.index is None else raw[o.index:o.index + 1]
            ref = want if o.index is None else want[o.index:o.index + 1]
            got = raw * factor(o.name)
            assert np.abs(ref).max() > 0, o.name          # (a zero would prove nothing)
            np.testing.assert_allclose(got, ref, rtol=1e-5, atol=2.0 ** -(o.frac or 0) * 2,
                                       err_msg=o.name)
    # the outputs' scalings: duty Q15, the estimates in um
    assert factor("out.duty_q15") == 2.0 ** -15 and factor("out.road_est_um") == 1e-6


@pytest.mark.skipif(shutil.which("gcc") is None or shutil.which("ld") is None,
                    reason="needs gcc and ld")
def test_every_address_is_where_gcc_lays_the_object_out(tmp_path):
    """The image's C (packed structs, one per segment in its section, placed by the linker
    script) compiled and linked: each segment's symbol is at its base (nm), and each
    object's offset and size in its struct, as gcc computes them, are the A2L's."""
    for name in (image_c.HEADER, image_c.SOURCE, image_c.LINKER):
        shutil.copy(GENERATED / name, tmp_path / name)
    subprocess.run(["gcc", "-std=c11", "-Wall", "-Werror", "-c", image_c.SOURCE, "-o",
                    "image.o"], cwd=tmp_path, check=True)
    subprocess.run(["ld", "-T", image_c.LINKER, "image.o", "-o", "image.elf"], cwd=tmp_path,
                   check=True)
    nm = subprocess.run(["nm", "image.elf"], cwd=tmp_path, check=True, capture_output=True,
                        text=True).stdout
    symbols = {line.split()[2]: int(line.split()[0], 16) for line in nm.splitlines()}
    assert symbols["ecu_epk"] == IMAGE.segment("IDENT").base
    lines = ['#include <stdio.h>', '#include <stddef.h>', f'#include "{image_c.HEADER}"',
             "int main(void) {"]
    for seg, (_, sym) in image_c.SYMBOLS.items():
        assert symbols[sym] == IMAGE.segment(seg).base, sym
    objs = list(IMAGE.objects.values())
    for o in objs:
        if o.segment == "IDENT":
            continue
        sym = image_c.SYMBOLS[o.segment][1]
        member = f"{sym}.{'.'.join(o.path)}" + (f"[{o.index}]" if o.index is not None else "")
        lines.append(f'  printf("%ld %zu\\n", (long)((char *)&{member} - (char *)&{sym}), '
                     f"sizeof({member}));")
    lines += ["  return 0;", "}"]
    (tmp_path / "offsets.c").write_text("\n".join(lines) + "\n")
    subprocess.run(["gcc", "-std=c11", "-Wall", "-Werror", "offsets.c", "image.o", "-o",
                    "offsets"], cwd=tmp_path, check=True)
    out = subprocess.run(["./offsets"], cwd=tmp_path, check=True, capture_output=True,
                         text=True).stdout.split("\n")
    rows = [o for o in objs if o.segment != "IDENT"]
    assert len(rows) > 500
    for o, line in zip(rows, out):
        off, size = map(int, line.split())
        base = symbols[image_c.SYMBOLS[o.segment][1]]
        assert (base + off, size) == (o.address, o.size), o.name


def test_the_epk_names_what_the_a2l_says_of_the_memory():
    """One A2L serves every mode of a car; another car (the SUV: the same layout, other
    limits and fixed-point formats) or a scaled gain row has another EPK, so a master holding
    the default car's A2L is refused by the tool instead of reading wrong physical values."""
    from calib import calpage
    from hil.config import load_vehicle
    from hil.nodes.sil import ecu_params

    cfg = default_vehicle()
    epks = {m: Image(ecu_params(cfg, m)).epk for m in ("auto", "comfort", "safety")}
    assert set(epks.values()) == {IMAGE.epk}, epks
    suv = Image(ecu_params(load_vehicle(ROOT / "hil" / "vehicles" / "suv.toml"), "auto"))
    assert suv.P.dtype == IMAGE.P.dtype and suv.T.dtype == IMAGE.T.dtype    # (same layout)
    p = IMAGE.params
    halved = calpage.replace_path(p, ("control", "k_safety"), 0.5 * np.asarray(
        p.control.k_safety))
    assert len({IMAGE.epk, suv.epk, Image(halved).epk}) == 3
