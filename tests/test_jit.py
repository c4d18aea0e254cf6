"""The compiled kernels (firmware.kernels, hil.kernels): the same bits as the interpreter, and
right answers where they replaced numpy/LAPACK calls."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from firmware.kernels import akf as akf_kernels
from hil.cli import _clean
from hil.config import default_vehicle
from hil.nodes import sil
from hil.sim.plant import QuarterCarPlant
from hil.sim.road import constant_route, load_route
from hil.validate import ride

ROOT = Path(__file__).resolve().parents[1]
CFG = default_vehicle()


def test_compiled_and_interpreted_runs_give_the_same_report():
    """``hil sim`` with NUMBA_DISABLE_JIT=1 (every kernel run by the interpreter) against the
    compiled run in this process: the whole report, trace hash and energy ledger included,
    is identical (IEEE arithmetic in a fixed order, no fast-math). On this stretch the R-hat
    guard acts (the eigen-decomposition path)."""
    args = [sys.executable, "-m", "hil", "sim", "--route", "full_road_section", "--mode",
            "auto", "--seed", "3", "--duration", "4", "--json"]
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    res = subprocess.run(args, capture_output=True, text=True, cwd=ROOT, env=env, timeout=900)
    assert res.returncode == 0, res.stderr[-2000:]
    interpreted = json.loads(res.stdout)
    route = load_route("full_road_section")
    compiled, _ = sil.run(CFG, route, "auto", 3, duration_s=4.0)
    ride.attach(compiled, CFG, route, sil.ecu_params(CFG, "auto"))    # (as hil sim judges)
    compiled = json.loads(json.dumps(_clean(compiled)))      # (NaN as the CLI writes it)
    assert compiled["segments"][0]["scored"]                  # (4 s: 1 s past the settling)
    assert interpreted["akf_r_guard_hits"] > 0
    assert interpreted == compiled


@pytest.mark.parametrize("n", [2, 3, 4, 6])
def test_jacobi_eigen_decomposition(n):
    rng = np.random.default_rng(n)
    for _ in range(50):
        A = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-6, 6)
        A = A + A.T
        w, V = akf_kernels.jacobi_eigh(A)
        assert np.allclose(np.sort(w), np.linalg.eigvalsh(A), rtol=1e-10,
                           atol=1e-12 * np.abs(A).max())
        assert np.allclose(V.T @ V, np.eye(n), atol=1e-12)
        assert np.allclose((V * w) @ V.T, A, rtol=1e-10, atol=1e-12 * np.abs(A).max())


@pytest.mark.parametrize("n", [2, 3, 4, 5])
def test_symmetric_solve_against_lapack(n):
    rng = np.random.default_rng(10 + n)
    for _ in range(50):
        L = rng.normal(size=(n, n))
        S = L @ L.T + n * np.eye(n)
        B = rng.normal(size=(n, 5))
        assert np.allclose(akf_kernels.solve_sym(S, B), np.linalg.solve(S, B), rtol=1e-10, atol=1e-12)
    singular = np.zeros((n, n))
    assert np.all(np.isnan(akf_kernels.solve_sym(singular, np.ones((n, 2)))))


def guard_r(R, floor):
    out = np.empty_like(R)
    hit = akf_kernels.guard(R, floor, np.outer(np.sqrt(floor), np.sqrt(floor)), out)
    return out, hit


def test_guard_clips_eigenvalues_for_any_size():
    rng = np.random.default_rng(7)
    for n in (2, 3, 4):
        floor = 10.0 ** rng.uniform(-6, 0, n)
        s = np.sqrt(floor)
        A = rng.normal(size=(n, n))
        R = (A @ A.T - 0.5 * np.eye(n)) * np.outer(s, s)      # some eigenvalues below floor
        G, hit = guard_r(R, floor)
        w = np.linalg.eigvalsh(G / np.outer(s, s))
        assert hit and w.min() >= 1.0 - 1e-9 and np.allclose(G, G.T)
        ok = np.diag(floor) * 4.0
        G2, hit2 = guard_r(ok, floor)
        assert not hit2 and np.array_equal(G2, ok)


def test_passive_run_is_the_step_loop():
    """The plant's compiled open-bridge loop (the passive twin) gives exactly what stepping it
    one tick at a time gives, bump stops and lift-off included (a rough road, fast)."""
    import dataclasses

    nl = dataclasses.replace(CFG.nonlinear, bump_stops=True, tire_lift_off=True)
    cfg = dataclasses.replace(CFG, nonlinear=nl)
    from hil.sim.drive import road_at_ticks
    from hil.sim.road import drive_timeline, generate_profile

    route = constant_route("F", 30.0, 2.0)
    zf = road_at_ticks(generate_profile(route, 1), drive_timeline(route, cfg.sim.plant_dt_s))
    a = QuarterCarPlant(cfg, actuator=False)
    b = QuarterCarPlant(cfg, actuator=False)
    a.reset(zf[0])
    b.reset(zf[0])
    rows = []
    for z in zf[1:]:
        a.step(z, enable=False)
        ba, _ = a.accelerations()
        rows.append((ba, a.x[2] - a.x[3], a.x[3] - a.zf, a.x[0] - a.x[1]))
    out = {}
    for lo in range(0, len(zf) - 1, 700):                   # in chunks, as the plant node does
        part = b.run_passive(zf[lo + 1:lo + 701])
        for k, v in part.items():
            out.setdefault(k, []).append(v)
    got = np.column_stack([np.concatenate(out[k]) for k in ("ba", "sws", "dtd", "vrel")])
    assert np.array_equal(got, np.array(rows))
    assert a.bump_contacts == b.bump_contacts > 0
    assert a.lift_off_events == b.lift_off_events > 0
    assert np.array_equal(a.x, b.x)


def test_grade_interpolation_is_numpys():
    from firmware.kernels.grade import interp

    xp = np.array([0.0, 5.0, 10.0, 20.0, 40.0, 70.0])
    fp = np.array([3.0e-3, 2.5e-3, 1.1e-3, 7.0e-4, 2.0e-4, 1.3e-4])
    rng = np.random.default_rng(2)
    xs = np.concatenate([xp, rng.uniform(-10.0, 90.0, 2000), [np.nan, -np.inf, np.inf]])
    got = np.array([interp(float(x), xp, fp) for x in xs])
    want = np.interp(xs, xp, fp)
    assert np.array_equal(got, want, equal_nan=True)


WARM_CHECK = """
import json
from numba.core.registry import CPUDispatcher
from firmware.kernels import akf, bppid, grade
from firmware import ecu as tick
from hil import nodes
from hil.nodes import sil
from hil.kernels import ecunode, plant, sensors
from hil.transport.codec import Codec
from hil.config import default_vehicle
from hil.sim.road import load_route

def kernels():
    out = {}
    for mod in (akf, bppid, grade, tick, ecunode, plant, sensors):
        for name, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher):
                out[mod.__name__ + "." + name] = len(obj.signatures)
    return out

cfg, codec = default_vehicle(), Codec()
ecu = nodes.EcuNode(sil.ecu_params(cfg, "auto"), codec, lockstep=False)
pl = nodes.PlantNode(cfg, load_route("full_road_section"), 1, codec)
app = sil.app_node(codec, "auto", pl.dt)
nodes.warm_up(ecu)
nodes.warm_up(pl)
before = kernels()
pl.n = 3000
nodes.run_in_process(pl, ecu, app)
print(json.dumps({"before": before, "after": kernels()}))
"""


def test_warm_up_leaves_nothing_to_compile_for_the_run():
    """After hil.nodes.warm_up, 3 s of a real run (speed, every controller path of auto mode
    on an A road, the twin) needs no kernel specialization the warm-up did not load (the
    ECU node's: its receive table and its tick, the ECU's every stage inside): a new
    one costs milliseconds inside a realtime tick (a non-contiguous calibration array once
    made the first real ECU tick 7.8 ms)."""
    res = subprocess.run([sys.executable, "-c", WARM_CHECK], capture_output=True, text=True,
                         cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout)
    assert got["before"] == got["after"]
    for kernel in ("hil.kernels.ecunode.receive", "hil.kernels.ecunode.tick",
                   "hil.kernels.ecunode.record", "hil.kernels.plant.advance",
                   "hil.kernels.plant.sensed", "hil.kernels.plant.observe_into",
                   "hil.kernels.sensors.quantise5"):
        assert got["before"][kernel] >= 1, kernel
