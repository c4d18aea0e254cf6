"""Vehicle configuration from TOML (stdlib ``tomllib``), the paper's Table 3 car by default.

The ``[vehicle]`` table and its five keys are a contract. The other tables describe the parts
the paper leaves open (actuator, sensors, nonlinearities); every key has a documented default
in ``hil/vehicles/table3.toml`` and may be overridden in a user file.

Every problem with a file raises :class:`ConfigError`, whose message is one line naming the
file and the key. CLIs turn it into that line on stderr and exit code 2.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from calib.errors import ConfigError, read_toml
from firmware.params import CTRL_NAMES, MODE_ENERGY, MODE_NAMES

PACKAGE_DIR = Path(__file__).resolve().parent
DEFAULT_VEHICLE_FILE = PACKAGE_DIR / "vehicles" / "table3.toml"

GRAVITY_MPS2 = 9.80665


def _number(path: Path, key: str, value: Any, *, positive: bool, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{path}: key '{key}' must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(f"{path}: key '{key}' must be finite, got {value}")
    if positive and (value < 0.0 or (value == 0.0 and not allow_zero)):
        bound = "non-negative" if allow_zero else "positive"
        raise ConfigError(f"{path}: key '{key}' must be {bound}, got {value}")
    return value


def build_section(cls: type, table: Any, path: Path, name: str, base: Any = None,
                  required: bool = False) -> Any:
    """Build dataclass ``cls`` from TOML ``table`` strictly: unknown keys, wrong types and
    out-of-range values are errors. Fields missing from ``table`` take ``base``'s value (or the
    dataclass default) unless ``required``. Field metadata: ``positive`` (default True),
    ``allow_zero``, ``upper`` (inclusive bound), ``integer``."""
    if table is None:
        table = {}
    if not isinstance(table, Mapping):
        raise ConfigError(f"{path}: '{name}' must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in table:
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(f"{path}: unknown key '{name}.{key}' (known: {known})")
    values = {}
    for fname, field in fields.items():
        full = f"{name}.{fname}"
        if fname not in table:
            if required:
                raise ConfigError(f"{path}: missing key '{full}'")
            if base is not None:
                values[fname] = getattr(base, fname)
            continue
        raw = table[fname]
        meta = field.metadata
        if meta.get("integer"):
            if isinstance(raw, bool) or not isinstance(raw, int):
                raise ConfigError(f"{path}: key '{full}' must be an integer, got {raw!r}")
            lo, hi = meta.get("range", (1, 2**31))
            if not lo <= raw <= hi:
                raise ConfigError(f"{path}: key '{full}' must be in [{lo}, {hi}], got {raw}")
            values[fname] = raw
            continue
        if meta.get("kind") == "bool":
            if not isinstance(raw, bool):
                raise ConfigError(f"{path}: key '{full}' must be true or false, got {raw!r}")
            values[fname] = raw
            continue
        value = _number(path, full, raw, positive=meta.get("positive", True),
                        allow_zero=meta.get("allow_zero", False))
        upper = meta.get("upper")
        if upper is not None and value > upper:
            raise ConfigError(f"{path}: key '{full}' must be <= {upper}, got {value}")
        values[fname] = value
    return cls(**values)


def _pos(**extra: Any) -> Any:
    return dataclasses.field(metadata={"positive": True, **extra})


def _nonneg() -> Any:
    return dataclasses.field(metadata={"positive": True, "allow_zero": True})


@dataclass(frozen=True)
class VehicleParams:
    """Quarter-car parameters (paper Table 3)."""

    sprung_mass_kg: float = _pos()
    unsprung_mass_kg: float = _pos()
    spring_stiffness_n_per_m: float = _pos()
    damping_n_s_per_m: float = _pos()
    tire_stiffness_n_per_m: float = _pos()

    @property
    def static_tire_load_n(self) -> float:
        return (self.sprung_mass_kg + self.unsprung_mass_kg) * GRAVITY_MPS2


@dataclass(frozen=True)
class ActuatorParams:
    """Ball-screw DC motor driven by an H-bridge; regeneration into a storage element."""

    screw_lead_m: float = _pos()
    torque_constant_nm_per_a: float = _pos()
    winding_resistance_ohm: float = _pos()
    winding_inductance_h: float = _pos()
    screw_efficiency: float = dataclasses.field(metadata={"positive": True, "upper": 1.0})
    viscous_friction_n_s_per_m: float = _nonneg()
    current_limit_a: float = _pos()
    bus_voltage_v: float = _pos()
    storage_voltage_v: float = _pos()

    @property
    def force_constant_n_per_a(self) -> float:
        """Ideal (lossless) force per ampere: K_t * 2*pi / lead; equals the back-EMF V/(m/s)."""
        return self.torque_constant_nm_per_a * 2.0 * math.pi / self.screw_lead_m


@dataclass(frozen=True)
class NonlinearParams:
    """Optional nonlinearities of the plant (off by default: the paper's model is linear)."""

    bump_stops: bool = dataclasses.field(metadata={"kind": "bool"})
    bump_stop_clearance_m: float = _pos()
    bump_stop_stiffness_n_per_m: float = _pos()
    tire_lift_off: bool = dataclasses.field(metadata={"kind": "bool"})


@dataclass(frozen=True)
class SensorChannel:
    """One analogue channel: Gaussian noise then an ADC with ``bits`` over [min, max]."""

    noise_std: float = _nonneg()
    range_min: float = dataclasses.field(metadata={"positive": False})
    range_max: float = dataclasses.field(metadata={"positive": False})
    bits: int = dataclasses.field(metadata={"integer": True, "range": (2, 24)})

    @property
    def lsb(self) -> float:
        return (self.range_max - self.range_min) / (2**self.bits - 1)


SENSOR_NAMES = ("body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")
# every channel of [sensors]: the five above (sampled together, hil.sensors.SensorSuite) and
# the supply voltage (sampled every 10 ms with its own noise stream)
SENSOR_KEYS = (*SENSOR_NAMES, "supply_voltage")


@dataclass(frozen=True)
class SensorParams:
    body_accel: SensorChannel
    wheel_accel: SensorChannel
    susp_defl: SensorChannel
    motor_current: SensorChannel
    speed: SensorChannel
    supply_voltage: SensorChannel


@dataclass(frozen=True)
class SimParams:
    plant_dt_s: float = dataclasses.field(metadata={"positive": True, "upper": 0.01})


@dataclass(frozen=True)
class VehicleConfig:
    """Everything a vehicle file defines."""

    vehicle: VehicleParams
    actuator: ActuatorParams
    nonlinear: NonlinearParams
    sensors: SensorParams
    sim: SimParams
    source: str = "<default>"


_TOP_LEVEL = ("vehicle", "actuator", "nonlinear", "sensors", "sim")


def _parse(data: Mapping[str, Any], path: Path, base: VehicleConfig | None) -> VehicleConfig:
    for key in data:
        if key not in _TOP_LEVEL:
            raise ConfigError(f"{path}: unknown table or key '{key}' (known: {', '.join(_TOP_LEVEL)})")
    if "vehicle" not in data:
        raise ConfigError(f"{path}: missing table '[vehicle]'")
    vehicle = build_section(VehicleParams, data["vehicle"], path, "vehicle", required=True)
    actuator = build_section(ActuatorParams, data.get("actuator"), path, "actuator",
                             base.actuator if base else None, required=base is None)
    nonlinear = build_section(NonlinearParams, data.get("nonlinear"), path, "nonlinear",
                              base.nonlinear if base else None, required=base is None)
    sim = build_section(SimParams, data.get("sim"), path, "sim", base.sim if base else None,
                        required=base is None)
    sensors_table = data.get("sensors", {})
    if not isinstance(sensors_table, Mapping):
        raise ConfigError(f"{path}: 'sensors' must be a table")
    for key in sensors_table:
        if key not in SENSOR_KEYS:
            raise ConfigError(f"{path}: unknown key 'sensors.{key}' (known: {', '.join(SENSOR_KEYS)})")
    channels = {}
    for name in SENSOR_KEYS:
        channel = build_section(SensorChannel, sensors_table.get(name), path, f"sensors.{name}",
                                getattr(base.sensors, name) if base else None,
                                required=base is None)
        if channel.range_max <= channel.range_min:
            raise ConfigError(f"{path}: key 'sensors.{name}.range_max' must exceed range_min")
        channels[name] = channel
    if actuator.storage_voltage_v > 10 * actuator.bus_voltage_v:
        raise ConfigError(f"{path}: key 'actuator.storage_voltage_v' is implausibly high")
    return VehicleConfig(vehicle=vehicle, actuator=actuator, nonlinear=nonlinear,
                         sensors=SensorParams(**channels), sim=sim, source=str(path))


_DEFAULT: VehicleConfig | None = None


def default_vehicle() -> VehicleConfig:
    """The paper's Table 3 car with the project's default actuator and sensors."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = _parse(read_toml(DEFAULT_VEHICLE_FILE, "vehicle"), DEFAULT_VEHICLE_FILE, None)
    return _DEFAULT


def load_vehicle(path: str | Path | None) -> VehicleConfig:
    """Load a vehicle file. ``[vehicle]`` is required with all five keys; the other tables
    override the defaults key by key. ``None`` gives the default car."""
    if path is None:
        return default_vehicle()
    path = Path(path)
    cfg = _parse(read_toml(path, "vehicle"), path, default_vehicle())
    check_plausible(cfg, path)
    return cfg


MAX_MODE_DT = 0.5            # the fastest passive mode |lambda| * dt at most this (80 Hz at 1 kHz)
MAX_STATIC_DEFLECTION_M = (0.5, 0.1)   # spring, tyre under the static load
MAX_FORCE_N = 32767          # the actuator's peak force: within FORCE_CMD's range (int16 N)


def check_plausible(cfg: VehicleConfig, path) -> None:
    """Refuse, with the reason, a vehicle the bench cannot simulate or calibrate honestly:
    a passive mode too fast for the plant step (a feather-light mass, a rigid spring), a
    spring or tyre that sags more than ``MAX_STATIC_DEFLECTION_M`` under the static load, or
    an actuator whose peak force (force constant x current limit) leaves FORCE_CMD's int16
    range and the firmware's integer signals (so no overflow is possible downstream)."""
    from calib.model import mechanics

    vp, ap, dt = cfg.vehicle, cfg.actuator, cfg.sim.plant_dt_s
    A4 = mechanics(vp)[0]
    lam = np.linalg.eigvals(A4) if np.all(np.isfinite(A4)) else np.array([np.nan])
    if not np.all(np.isfinite(lam)):
        raise ConfigError(f"{path}: the vehicle's dynamics are not finite (check [vehicle])")
    fastest = float(np.max(np.abs(lam)))
    if fastest * dt > MAX_MODE_DT:
        raise ConfigError(
            f"{path}: the passive car's fastest mode ({fastest / (2 * math.pi):.4g} Hz) is too "
            f"fast for the plant step of {dt:g} s (at most "
            f"{MAX_MODE_DT / dt / (2 * math.pi):.3g} Hz): check the masses and stiffnesses")
    sag = (vp.sprung_mass_kg * GRAVITY_MPS2 / vp.spring_stiffness_n_per_m,
           vp.static_tire_load_n / vp.tire_stiffness_n_per_m)
    for what, value, limit in zip(("spring_stiffness_n_per_m", "tire_stiffness_n_per_m"),
                                  sag, MAX_STATIC_DEFLECTION_M):
        if value > limit:
            raise ConfigError(f"{path}: vehicle.{what} sags {value:.3g} m under the static "
                              f"load (at most {limit:g} m)")
    peak = ap.force_constant_n_per_a * ap.current_limit_a
    if not peak <= MAX_FORCE_N:
        raise ConfigError(f"{path}: the actuator's peak force (force constant "
                          f"{ap.force_constant_n_per_a:.4g} N/A x current limit "
                          f"{ap.current_limit_a:g} A = {peak:.4g} N) exceeds {MAX_FORCE_N} N, "
                          f"FORCE_CMD's range: check screw_lead_m and torque_constant_nm_per_a")


REQUEST_KINDS = ("accept", "refuse", "choose")
# mode names of the files and the command line ("regen" = energy feedback)
# The names of the modes and controllers on the command line and in driver scripts: the
# firmware's (firmware.params.MODE_NAMES, CTRL_NAMES), energy feedback also as "regen".
MODE_BY_NAME = {**{name: i for i, name in enumerate(MODE_NAMES)}, "regen": MODE_ENERGY}
RUN_MODES = {name: i for name, i in MODE_BY_NAME.items() if name != "energy"}   # hil sim/run
MODE_CHOICES = ("auto", *RUN_MODES)
CONTROLLERS = {name: i for i, name in enumerate(CTRL_NAMES) if name != "none"}


def load_driver_script(path: str | Path) -> list[tuple[float, str, int | None]]:
    """A driver script: ``[[request]]`` tables with ``t_s`` (simulated seconds), ``kind``
    (accept | refuse | choose) and ``mode`` (needed for choose; for accept it must be the mode
    recommended then, and may be left out). Returns [(t_s, kind, mode or None), ...]."""
    path = Path(path)
    data = read_toml(path, "driver script")
    extra = set(data) - {"request", "description"}
    if extra:
        raise ConfigError(f"{path}: unknown key '{sorted(extra)[0]}' (expected [[request]] tables)")
    reqs = data.get("request")
    if not isinstance(reqs, list) or not reqs or not all(isinstance(r, dict) for r in reqs):
        raise ConfigError(f"{path}: needs at least one [[request]] table")
    out = []
    for i, r in enumerate(reqs):
        key = f"request[{i}]"
        extra = set(r) - {"t_s", "kind", "mode"}
        if extra:
            raise ConfigError(f"{path}: unknown key '{key}.{sorted(extra)[0]}'")
        if "t_s" not in r:
            raise ConfigError(f"{path}: key '{key}.t_s' is missing")
        t = _number(path, f"{key}.t_s", r["t_s"], positive=True, allow_zero=True)
        kind = r.get("kind")
        if kind not in REQUEST_KINDS:
            raise ConfigError(f"{path}: key '{key}.kind' must be one of "
                              f"{', '.join(REQUEST_KINDS)}, got {kind!r}")
        mode = r.get("mode")
        if mode is None and kind == "choose":
            raise ConfigError(f"{path}: key '{key}.mode' is needed for kind 'choose'")
        if mode is not None and mode not in MODE_BY_NAME:
            raise ConfigError(f"{path}: key '{key}.mode' must be one of "
                              f"{', '.join(MODE_BY_NAME)}, got {mode!r}")
        out.append((t, kind, None if mode is None else MODE_BY_NAME[mode]))
    return sorted(out, key=lambda e: e[0])
