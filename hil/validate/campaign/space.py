"""A campaign's vehicle space (``[space]``): named parameter ranges sampled by a seeded
quasi-random design (``scipy.stats.qmc``), so the same file gives the same cars.

    [space]
    samples = 128                     # cars per [[vehicle]] (each base car gets its own)
    sampler = "lhs"                   # lhs (Latin hypercube) or sobol (scrambled)
    seed = 1
    calibration = "per-car"           # per-car: each car designed for itself;
                                      # nominal: every car driven by its base car's calibration
    [space.ranges]                    # a factor range on the base car's value,
    sprung_mass_kg = [1.0, 1.3]       # or an absolute one: {min = 320.0, max = 420.0}
    tire_stiffness_n_per_m = [0.8, 1.2]

A car's factors are rounded to six significant digits (its identity in the database reads
back the same). A car the bench cannot simulate or calibrate is not run: it is recorded with
the reason (``hil.validate.campaign.spec``)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Optional

from calib.errors import ConfigError
from calib.vehicle import VehicleParams

# the keys of a vehicle file's [vehicle] table (a campaign's factors may name them)
VEHICLE_KEYS = tuple(f.name for f in dataclasses.fields(VehicleParams))
# the keys a range may name, and the table of the vehicle file each belongs to
SPACE_KEYS = {**{k: "vehicle" for k in VEHICLE_KEYS}, "torque_constant_nm_per_a": "actuator",
              "winding_resistance_ohm": "actuator"}
SAMPLERS = ("lhs", "sobol")
CALIBRATIONS = ("per-car", "nominal")
MAX_SAMPLES = 4096
MAX_FACTOR = 10.0


@dataclasses.dataclass(frozen=True)
class Space:
    samples: int
    sampler: str
    seed: int
    calibration: str
    ranges: tuple[tuple[str, str, float, float], ...]   # (key, "factor" | "value", lo, hi)


def parse(path: Path, table: Any) -> Optional[Space]:
    """The ``[space]`` table (None when absent); ConfigError (one line) on anything wrong."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [space] must be a table")
    known = ("samples", "sampler", "seed", "calibration", "ranges")
    for key in table:
        if key not in known:
            raise ConfigError(f"{path}: unknown key 'space.{key}' ({', '.join(known)})")
    n = table.get("samples")
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_SAMPLES:
        raise ConfigError(f"{path}: space.samples must be an integer in [1, {MAX_SAMPLES}]")
    sampler = table.get("sampler", "lhs")
    if sampler not in SAMPLERS:
        raise ConfigError(f"{path}: space.sampler must be one of {', '.join(SAMPLERS)}")
    seed = table.get("seed", 1)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{path}: space.seed must be a non-negative integer")
    calibration = table.get("calibration", "per-car")
    if calibration not in CALIBRATIONS:
        raise ConfigError(f"{path}: space.calibration must be one of {', '.join(CALIBRATIONS)}")
    raw = table.get("ranges")
    if not isinstance(raw, dict) or not raw:
        raise ConfigError(f"{path}: [space.ranges] must name at least one parameter "
                          f"({', '.join(SPACE_KEYS)})")
    ranges = []
    for key, value in raw.items():
        if key not in SPACE_KEYS:
            raise ConfigError(f"{path}: space.ranges.{key}: one of {', '.join(SPACE_KEYS)}")
        ranges.append((key, *_range(path, key, value)))
    return Space(n, sampler, seed, calibration, tuple(ranges))


def _range(path: Path, key: str, value: Any) -> tuple[str, float, float]:
    where = f"{path}: space.ranges.{key}"
    if isinstance(value, list):
        kind, pair = "factor", value
    elif isinstance(value, dict) and set(value) == {"min", "max"}:
        kind, pair = "value", [value["min"], value["max"]]
    else:
        raise ConfigError(f"{where}: a factor range [lo, hi] or {{min = ..., max = ...}}")
    if len(pair) != 2 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                 and math.isfinite(x) and x > 0 for x in pair):
        raise ConfigError(f"{where}: two positive finite numbers")
    lo, hi = float(pair[0]), float(pair[1])
    if not lo <= hi:
        raise ConfigError(f"{where}: the lower end {lo:g} exceeds the upper {hi:g}")
    if kind == "factor" and hi > MAX_FACTOR:
        raise ConfigError(f"{where}: factors at most {MAX_FACTOR:g}")
    return kind, lo, hi


def unit_points(space: Space) -> list[list[float]]:
    """``samples`` points in [0, 1)^d, d the number of ranges: the seeded design."""
    from scipy.stats import qmc

    d = len(space.ranges)
    if space.sampler == "lhs":
        gen = qmc.LatinHypercube(d=d, seed=space.seed)
    else:
        gen = qmc.Sobol(d=d, scramble=True, seed=space.seed)
    return gen.random(space.samples).tolist()


def factors(space: Space, base: dict[str, float]) -> list[dict[str, float]]:
    """Each car's factors on its base car's values (``base``: key -> the base car's value),
    in sample order, rounded to six significant digits."""
    out = []
    for u in unit_points(space):
        car = {}
        for (key, kind, lo, hi), x in zip(space.ranges, u):
            v = lo + x * (hi - lo)
            car[key] = float(f"{(v / base[key] if kind == 'value' else v):.6g}")
        out.append(car)
    return out
