"""The C fixed-point path built and fed as its tests and benchmarks do: gcc at fixed flags
(C99, every warning an error, ``-O2``) over ``c/`` and the generated tables, and a recorded
trace as the stdin of ``c/trace_replay.c``."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
C_DIR = ROOT / "c"
GEN = C_DIR / "generated"
# -ffp-contract=off: no fused multiply-add, so that the double estimator (c/akf_cov.c) rounds
# every product as Python does
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-ffp-contract=off")


def replay_sources(gen: Path = GEN) -> tuple:
    """``trace_replay``'s sources with the tables of ``gen``."""
    return (C_DIR / "ecu_fx.c", C_DIR / "akf_cov.c", C_DIR / "trace_replay.c",
            gen / "ecu_tables.c")


REPLAY_SOURCES = replay_sources()
LIBS = ("-lm",)


class CBuildError(RuntimeError):
    pass


def gcc() -> str:
    cc = shutil.which("gcc")
    if not cc:
        raise CBuildError("gcc is needed for the C path (Debian: apt-get install gcc)")
    return cc


def compile_c(out: Path, sources, *extra, gen: Path = GEN) -> Path:
    """Compile ``sources`` to ``out`` against the tables header in ``gen``; a warning or an
    error raises CBuildError with the command and gcc's output."""
    cmd = [gcc(), *CFLAGS, f"-I{gen}", f"-I{C_DIR}", *extra, *map(str, sources), "-o",
           str(out), *(() if "-c" in extra else LIBS)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0 or res.stderr:
        raise CBuildError(f"{' '.join(cmd)}\n{res.stderr}")
    return Path(out)


def replay_input(rec) -> str:
    """A fixed-point run's record (``hil.nodes.sil.run(fx_record=...)``: per tick the
    ``firmware.fx.state.TickIn`` and the outputs) as ``trace_replay``'s stdin."""
    def line(i):
        counts = [-1 if v is None else v for v in i.counts]
        return " ".join(map(str, [*counts, *i.k_q, *i.r_q, i.want, int(i.passive),
                                  int(i.fault), int(i.regen), int(i.reset)]))
    return "\n".join(line(i) for i, _ in rec) + "\n"


def replay_cov_input(rec) -> str:
    """The same record as ``trace_replay --cov``'s stdin: the counts, the covariance side's
    inputs (q_road bit for bit, as a hex float; its flags) and the mode's."""
    def line(i):
        counts = [-1 if v is None else v for v in i.counts]
        return " ".join(map(str, [*counts, float(i.q_road).hex(), i.cov_flags, i.want,
                                  int(i.passive), int(i.fault), int(i.regen)]))
    return "\n".join(line(i) for i, _ in rec) + "\n"


def parse_cov_output(text: str, m: int = 3) -> tuple:
    """``trace_replay --cov``'s lines as (outputs: the tuples ``replay_input``'s replay
    gives, k_q, r_q, K: the float gain's exact values)."""
    n_out = 2 + 5 + m + 2
    outs, kq, rq, kf = [], [], [], []
    for line in text.splitlines():
        f = line.split()
        outs.append(tuple(int(v) for v in f[:n_out]))
        kq.append(tuple(int(v) for v in f[n_out:n_out + 5 * m]))
        rq.append(tuple(int(v) for v in f[n_out + 5 * m:n_out + 6 * m]))
        kf.append(tuple(float.fromhex(v) for v in f[n_out + 6 * m:]))
    return outs, kq, rq, kf


PARITY_S = 80.0   # the full road section's first 80 s: A, B, C and the start of D (every controller)


def full_road_trace(seconds: float = PARITY_S) -> list:
    """The parity trace of the full road section (auto mode, seed 1, fixed point): the
    record of ``hil.nodes.sil.run(fx_record=...)`` and the run's report."""
    from hil.config import default_vehicle
    from hil.nodes import sil
    from hil.sim.road import load_route

    rec = []
    report, _ = sil.run(default_vehicle(), load_route("full_road_section"), "auto", 1,
                        fixed_point=True, fx_record=rec, duration_s=seconds)
    return rec, report


def bump_stop_vehicle():
    """The default car with its bump stops and tyre lift-off modelled (``bump_stop_trace``)."""
    import dataclasses

    from hil.config import default_vehicle

    cfg = default_vehicle()
    return dataclasses.replace(cfg, nonlinear=dataclasses.replace(
        cfg.nonlinear, bump_stops=True, tire_lift_off=True), source="bump-stops")


def bump_stop_trace(work: Path) -> tuple:
    """Off the linear model: 450 m of a grade-D road at 30 m/s in safety mode on
    ``bump_stop_vehicle()``, hard enough to hit the bump stops. Returns (the vehicle, its
    tables' directory in ``work``, the record)."""
    from calib import c_tables
    from hil.nodes import sil
    from hil.sim.road import load_route

    cfg = bump_stop_vehicle()
    gen = work / "gen"
    gen.mkdir(parents=True, exist_ok=True)
    for name, text in c_tables.generate(cfg).items():
        (gen / name).write_text(text)
    route = work / "d30.toml"
    route.write_text('name = "d30"\n[[segment]]\ngrade = "D"\nlength_m = 450.0\n'
                     "speed_mps = 30.0\n")
    rec = []
    sil.run(cfg, load_route(route), "safety", 1, fixed_point=True, fx_record=rec)
    return cfg, gen, rec


def sensor_fault_trace() -> list:
    """6 s in comfort with the deflection sensor biased 3 mm from 2 s on: named, left out,
    the filter and the controllers restarted (the hand-over's reset), driven on."""
    from hil.config import default_vehicle
    from hil.nodes import sil
    from hil.sim.road import load_route

    rec = []
    sil.run(default_vehicle(), load_route("full_road_section"), "comfort", 2, fixed_point=True,
            fx_record=rec, duration_s=6.0, sensor_fault=("susp_defl", "bias", 2000, 0.003))
    return rec


def left_out_trace(at_tick: int = 1500, duration_s: float = 3.0) -> list:
    """3 s in comfort, the deflection sensor left out by hand between ticks ``at_tick`` - 1
    and ``at_tick`` (``firmware.ecu.Ecu.leave_out`` mid-drive, the three nodes in this
    process): the filter and the controllers restarted, driven on."""
    from hil.config import default_vehicle
    from hil.nodes import sil
    from hil.nodes.inprocess import run_in_process
    from hil.nodes.ecu import EcuNode
    from hil.nodes.plant import PlantNode
    from hil.sim.road import load_route
    from hil.transport import secoc
    from hil.transport.codec import Codec

    cfg, codec, key = default_vehicle(), Codec(), secoc.new_key()
    plant = PlantNode(cfg, load_route("full_road_section"), 2, codec, key=key)
    plant.n = int(round(duration_s / plant.dt))
    ecu = EcuNode(sil.ecu_params(cfg, "comfort"), codec, lockstep=True, fixed_point=True,
                  record=True, key=key)
    app = sil.app_node(codec, "comfort", cfg.sim.plant_dt_s, key=key)
    run_in_process(plant, ecu, app, until=at_tick)
    ecu.state.leave_out("susp_defl")
    run_in_process(plant, ecu, app)
    return ecu.state.log
