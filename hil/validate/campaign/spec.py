"""The campaign file, read and expanded into its cases (routes x seeds x vehicles x
modes x arithmetic x noise), and each case's vehicle and route."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import tomllib
from pathlib import Path
from typing import Optional

from calib.errors import ConfigError
from hil.validate.campaign.space import SPACE_KEYS, VEHICLE_KEYS, Space
from hil.validate.campaign.space import factors as space_factors
from hil.validate.campaign.space import parse as parse_space


@dataclasses.dataclass(frozen=True)
class Campaign:
    name: str
    cases: tuple[dict, ...]
    acceptance: bool | str          # True, False or "relative"
    max_gap: Optional[float]
    infeasible: tuple[dict, ...] = ()   # sampled cars not run: {"vehicle": spec, "reason": ...}


def load(path: str | Path) -> Campaign:
    """Read and expand a campaign file; ConfigError (one line) on anything wrong."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    for key in data:
        if key not in ("campaign", "vehicle", "criteria", "nonlinear", "space"):
            raise ConfigError(f"{path}: unknown table '{key}' (campaign, vehicle, criteria, "
                              "nonlinear, space)")
    c = data.get("campaign")
    if not isinstance(c, dict):
        raise ConfigError(f"{path}: missing table [campaign]")
    known = ("name", "routes", "seeds", "modes", "fixed_point", "noise", "duration_s")
    for key in c:
        if key not in known:
            raise ConfigError(f"{path}: unknown key 'campaign.{key}' ({', '.join(known)})")
    routes = [_route_spec(path, r) for r in _list(path, c, "routes", str, required=True)]
    seeds = _seeds(path, c.get("seeds", [1]))
    modes = _list(path, c, "modes", str, default=["auto"])
    from hil.config import MODE_CHOICES

    for m in modes:
        if m not in MODE_CHOICES:
            raise ConfigError(f"{path}: campaign.modes: {m!r} is not one of "
                              f"{', '.join(MODE_CHOICES)}")
    fixed = _list(path, c, "fixed_point", bool, default=[False])
    noise = [float(x) for x in _list(path, c, "noise", (int, float), default=[1.0])]
    if any(not (math.isfinite(x) and 0 <= x <= 100) for x in noise):
        raise ConfigError(f"{path}: campaign.noise: factors in [0, 100]")
    duration = c.get("duration_s")
    if duration is not None and not (isinstance(duration, (int, float))
                                     and math.isfinite(duration) and duration > 0):
        raise ConfigError(f"{path}: campaign.duration_s must be a positive number")
    nonlinear = _nonlinear(path, data.get("nonlinear"))
    space = parse_space(path, data.get("space"))
    vehicles, infeasible = [], []
    for table in data.get("vehicle") or [{}]:
        cars, out = _vehicles(path, table, nonlinear, space)
        vehicles += cars
        infeasible += out
    crit = data.get("criteria", {})
    max_gap = crit.get("max_gap")
    if max_gap is not None and not (isinstance(max_gap, (int, float)) and max_gap >= 0):
        raise ConfigError(f"{path}: criteria.max_gap must be a number >= 0")
    acceptance = crit.get("acceptance", True)
    if not isinstance(acceptance, bool) and acceptance != "relative":
        raise ConfigError(f"{path}: criteria.acceptance must be true, false or \"relative\"")
    cases = {}                           # (a case listed twice is one case)
    for r, s, v, m, f, n in itertools.product(routes, seeds, vehicles, modes, fixed, noise):
        case = new_case(r, s, v, m, f, n, duration)
        cases.setdefault(case_id(case), case)
    cases = tuple(cases.values())
    return Campaign(str(c.get("name", path.stem)), cases, acceptance,
                    None if max_gap is None else float(max_gap), tuple(infeasible))


def new_case(route: dict, seed: int, vehicle: dict, mode: str = "auto", fixed_point: bool = False,
             noise: float = 1.0, duration_s: Optional[float] = None) -> dict:
    """One case: what ``case_id`` digests and a worker runs."""
    return {"route": route, "seed": seed, "vehicle": vehicle, "mode": mode,
            "fixed_point": fixed_point, "noise": noise, "duration_s": duration_s}


def _list(path, table, key, kind, default=None, required=False) -> list:
    if key not in table:
        if required:
            raise ConfigError(f"{path}: missing key 'campaign.{key}'")
        return list(default)
    value = table[key]
    if not isinstance(value, list):
        value = [value]
    if not value or not all(isinstance(x, kind) and not (kind is not bool and
                                                          isinstance(x, bool)) for x in value):
        raise ConfigError(f"{path}: campaign.{key}: a non-empty list of the right type")
    return value


def _seeds(path, value) -> list[int]:
    if isinstance(value, dict):
        lo, hi = value.get("from"), value.get("to")
        if not (isinstance(lo, int) and isinstance(hi, int) and 0 <= lo <= hi):
            raise ConfigError(f"{path}: campaign.seeds: {{from = N, to = M}} with 0 <= N <= M")
        return list(range(lo, hi + 1))
    if not isinstance(value, list):
        value = [value]
    if not value or not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0
                            for x in value):
        raise ConfigError(f"{path}: campaign.seeds: a list of integers >= 0")
    return value


def _route_spec(path: Path, r: str) -> dict:
    """A shipped route by name, or a route file's text (the worker needs no disk)."""
    from hil.sim.road import load_route

    p = (path.parent / r) if not Path(r).is_absolute() else Path(r)
    if r.endswith(".toml"):
        if not p.is_file():
            p = Path(r)
        try:
            load_route(str(p))
        except (ConfigError, OSError, ValueError) as exc:
            raise ConfigError(f"{path}: route {r}: {exc}") from None
        return {"name": p.stem, "toml": p.read_text()}
    try:
        load_route(r)
    except (ConfigError, ValueError) as exc:
        raise ConfigError(f"{path}: route {r}: {exc}") from None
    return {"name": r}


def _nonlinear(path: Path, table) -> dict:
    """The campaign's [nonlinear] table: keys of a vehicle file's [nonlinear], set on every
    vehicle (checked here by the vehicle file's own reader, on the default car: unknown keys,
    types and ranges, in one line)."""
    if table is None:
        return {}
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [nonlinear] must be a table")
    vehicle_config({"name": "default", "toml": None, "factors": {}, "nonlinear": table}, 1.0,
                   f"{path}: ")
    return dict(table)


def _vehicles(path: Path, table: dict, nonlinear: dict, space: Optional[Space] = None
              ) -> tuple[list[dict], list[dict]]:
    """A [[vehicle]] table: its file as text (none: the default car) and each combination of
    its factor lists, or with a ``[space]`` each sampled car; ``nonlinear``: the campaign's
    [nonlinear] keys, on each. Returns (cars, infeasible): a listed variant the bench cannot
    simulate is an error now, a sampled one is recorded with the reason."""
    from hil.config import load_vehicle

    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [[vehicle]] must be a table")
    file = table.get("file")
    text, name = None, "default"
    if file is not None:
        p = path.parent / file if (path.parent / file).is_file() else Path(file)
        load_vehicle(p)                          # (its own errors, one line)
        text, name = p.read_text(), p.stem
    for key in table:
        if key != "file" and key not in VEHICLE_KEYS:
            raise ConfigError(f"{path}: vehicle key '{key}': file or one of "
                              f"{', '.join(VEHICLE_KEYS)}")
    if space is not None:
        if set(table) - {"file"}:
            raise ConfigError(f"{path}: [[vehicle]] {name}: factor lists and a [space] (one "
                              "or the other)")
        return _sampled(path, {"name": name, "toml": text, "factors": {}}, nonlinear, space)
    axes = []
    for key in VEHICLE_KEYS:
        if key in table:
            vals = table[key] if isinstance(table[key], list) else [table[key]]
            if not vals or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                   and 0 < x < 10 for x in vals):
                raise ConfigError(f"{path}: vehicle.{key}: factors in (0, 10)")
            axes.append([(key, float(x)) for x in vals])
    out = []
    for combo in itertools.product(*axes) if axes else [()]:
        factors = {k: v for k, v in combo if v != 1.0}
        spec = {"name": name, "toml": text, "factors": factors}
        if nonlinear:                     # (absent when empty: earlier cases keep their ids)
            spec["nonlinear"] = nonlinear
        if factors:                       # a variant the bench cannot simulate: said now
            from calib.model import check_plausible

            check_plausible(vehicle_config(spec, 1.0), f"{path}: vehicle {label(spec)}")
        out.append(spec)
    return out, []


def _sampled(path: Path, base: dict, nonlinear: dict, space: Space
             ) -> tuple[list[dict], list[dict]]:
    """The space's cars around ``base``: each checked as a listed variant is; one the bench
    cannot simulate or calibrate is recorded with the reason, not run."""
    from calib.model import check_plausible

    if nonlinear:
        base = {**base, "nonlinear": nonlinear}
    cfg = vehicle_config(base, 1.0)
    values = {k: getattr(getattr(cfg, table), k) for k, table in SPACE_KEYS.items()}
    cars, infeasible = [], []
    for i, f in enumerate(space_factors(space, values)):
        spec = {**base, "factors": {k: v for k, v in f.items() if v != 1.0}, "sample": i + 1}
        if space.calibration == "nominal":
            spec["calibration"] = "nominal"
        try:
            check_plausible(vehicle_config(spec, 1.0), f"car {i + 1}")
        except ConfigError as exc:
            infeasible.append({"vehicle": spec, "reason": str(exc)})
            continue
        cars.append(spec)
    return cars, infeasible


def label(spec: dict) -> str:
    car = f" car {spec['sample']}" if "sample" in spec else ""
    return spec["name"] + car + "".join(f" {k}x{v:g}" for k, v in sorted(spec["factors"].items()))


def case_id(case: dict) -> str:
    return hashlib.sha256(json.dumps(case, sort_keys=True).encode()).hexdigest()[:16]


def vehicle_config(spec: dict, noise: float, where: str = ""):
    """The case's vehicle: its file (or the default car), the factors on [vehicle], the
    campaign's [nonlinear] keys, the noise factor on every sensor. A car of a space's
    ``nominal`` calibration sits at the ride height of its base car's set-up: a heavier body
    or a softer spring sags (``calib.vehicle.static_sag_m``), which its deflection sensor
    reads and its bump stops feel; a car calibrated for itself has none."""
    from hil.config import DEFAULT_VEHICLE_FILE, default_vehicle

    from calib.vehicle import parse_vehicle
    base = default_vehicle()
    data = tomllib.loads(spec["toml"] or DEFAULT_VEHICLE_FILE.read_text())
    plain = None
    for key, factor in spec["factors"].items():
        table = SPACE_KEYS.get(key, "vehicle")
        if key not in data.get(table, {}):        # (a key the file leaves to the default car)
            plain = plain or vehicle_config({**spec, "factors": {}}, 1.0, where)
            data.setdefault(table, {})[key] = getattr(getattr(plain, table), key)
        data[table][key] = data[table][key] * factor
    if spec.get("nonlinear"):
        data["nonlinear"] = {**data.get("nonlinear", {}), **spec["nonlinear"]}
    cfg = parse_vehicle(data, Path(f"{where}<{label(spec)}>"), None if not spec["toml"] else base)
    if noise != 1.0:
        sensors = {f.name: dataclasses.replace(getattr(cfg.sensors, f.name),
                                               noise_std=getattr(cfg.sensors, f.name).noise_std
                                               * noise)
                   for f in dataclasses.fields(cfg.sensors)}
        cfg = dataclasses.replace(cfg, sensors=type(cfg.sensors)(**sensors))
    if spec.get("calibration") == "nominal" and spec["factors"]:
        from calib.vehicle import on_calibration

        cfg = on_calibration(cfg, vehicle_config(base_spec(spec), 1.0, where))
    return cfg


def base_spec(spec: dict) -> dict:
    """The car a space's car was sampled around: its file and [nonlinear], no factors (the
    car a nominal calibration is designed for, and whose ride height it keeps)."""
    return {**{k: v for k, v in spec.items() if k not in ("sample", "calibration")},
            "factors": {}}


def route_of(spec: dict):
    from hil.sim.road import load_route, parse_route

    if "toml" in spec:
        return parse_route(tomllib.loads(spec["toml"]), Path(f"<{spec['name']}>"), spec["name"])
    return load_route(spec["name"])
