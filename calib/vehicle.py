"""The vehicle's types: what a vehicle file defines (the paper's Table 3 car by default), and
its strict parsing from a TOML table.

The ``[vehicle]`` table and its five keys are a contract. The other tables describe the parts
the paper leaves open (actuator, sensors, nonlinearities); every key has a documented default
in ``hil/vehicles/table3.toml`` (read by ``hil.config``) and may be overridden in a user file.
Every problem raises :class:`~calib.errors.ConfigError`, whose message is one line naming the
file and the key. These types sit below the calibration (``calib.model`` designs against them)
and the bench (``hil`` simulates them)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from calib.errors import ConfigError

GRAVITY_MPS2 = 9.80665


def check_number(path: Path, key: str, value: Any, *, positive: bool,
                 allow_zero: bool = False) -> float:
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
    ``allow_zero``, ``upper`` (inclusive bound), ``range`` (the physical range: inclusive
    bounds, ``docs/plant.md``), ``integer``."""
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
            if required and field.default is dataclasses.MISSING:
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
        value = check_number(path, full, raw, positive=meta.get("positive", True),
                        allow_zero=meta.get("allow_zero", False))
        upper = meta.get("upper")
        if upper is not None and value > upper:
            raise ConfigError(f"{path}: key '{full}' must be <= {upper}, got {value}")
        lo, hi = meta.get("range", (-math.inf, math.inf))
        if not lo <= value <= hi:
            raise ConfigError(f"{path}: key '{full}' must be in [{lo:g}, {hi:g}] (its "
                              f"physical range), got {value:g}")
        values[fname] = value
    return cls(**values)


def _pos(lo: float, hi: float, **extra: Any) -> Any:
    """A positive quantity within its physical range [lo, hi]."""
    return dataclasses.field(metadata={"positive": True, "range": (lo, hi), **extra})


def _nonneg(hi: float = math.inf) -> Any:
    return dataclasses.field(metadata={"positive": True, "allow_zero": True,
                                       "range": (0.0, hi)})


@dataclass(frozen=True)
class VehicleParams:
    """Quarter-car parameters (paper Table 3)."""

    # (the physical ranges: one corner of anything from a light quadricycle to a heavy truck)
    sprung_mass_kg: float = _pos(20.0, 5000.0)
    unsprung_mass_kg: float = _pos(2.0, 1000.0)
    spring_stiffness_n_per_m: float = _pos(1e3, 1e6)
    damping_n_s_per_m: float = _pos(10.0, 1e5)
    tire_stiffness_n_per_m: float = _pos(1e4, 1e7)

    @property
    def static_tire_load_n(self) -> float:
        return (self.sprung_mass_kg + self.unsprung_mass_kg) * GRAVITY_MPS2


@dataclass(frozen=True)
class ActuatorParams:
    """Ball-screw DC motor driven by an H-bridge; regeneration into a storage element."""

    screw_lead_m: float = _pos(1e-3, 0.1)
    torque_constant_nm_per_a: float = _pos(1e-3, 10.0)
    winding_resistance_ohm: float = _pos(1e-3, 100.0)
    winding_inductance_h: float = _pos(1e-6, 1.0)
    screw_efficiency: float = _pos(0.1, 1.0)
    viscous_friction_n_s_per_m: float = _nonneg(1e4)
    current_limit_a: float = _pos(0.1, 1000.0)
    bus_voltage_v: float = _pos(1.0, 1000.0)
    storage_voltage_v: float = _pos(1.0, 1000.0)

    @property
    def force_constant_n_per_a(self) -> float:
        """Ideal (lossless) force per ampere: K_t * 2*pi / lead; equals the back-EMF V/(m/s)."""
        return self.torque_constant_nm_per_a * 2.0 * math.pi / self.screw_lead_m


@dataclass(frozen=True)
class NonlinearParams:
    """Optional nonlinearities of the plant (off by default: the paper's model is linear)."""

    bump_stops: bool = dataclasses.field(metadata={"kind": "bool"})
    bump_stop_clearance_m: float = _pos(0.005, 0.5)
    bump_stop_stiffness_n_per_m: float = _pos(1e3, 1e8)
    tire_lift_off: bool = dataclasses.field(metadata={"kind": "bool"})
    # the suspension's static deflection from the ride height it was set up for (m; negative:
    # compressed, as a payload on a car calibrated empty: -g (m_s / k_s - m_s0 / k_s0)). The
    # deflection sensor reads it, the bump stops' clearance shifts by it (less stroke in
    # compression); the linear dynamics are the same about the new equilibrium. A key with a
    # default: a vehicle file need not name it.
    static_deflection_m: float = dataclasses.field(default=0.0, metadata={
        "positive": False, "range": (-0.5, 0.5)})


def static_sag_m(car: VehicleParams, design: VehicleParams) -> float:
    """The static deflection of ``car`` from the ride height of the car it was set up for
    (``design``): -g (m_s / k_s - m_s0 / k_s0), negative when the body sits lower (a payload,
    a softer spring). The spring alone carries the body: the unsprung mass and the tyre move
    the wheel, not the stroke."""
    return -GRAVITY_MPS2 * (car.sprung_mass_kg / car.spring_stiffness_n_per_m
                            - design.sprung_mass_kg / design.spring_stiffness_n_per_m)


def on_calibration(car: "VehicleConfig", calibration: "VehicleConfig") -> "VehicleConfig":
    """``car`` driven with the ECU of ``calibration``'s car: at the ride height that car was
    set up for (``static_sag_m``, added to its own static deflection), which the deflection
    sensor reads and the bump stops feel. The one path for a campaign space's ``nominal``
    calibration and ``--calibration FILE``; ``car`` itself when nothing moves."""
    sag = static_sag_m(car.vehicle, calibration.vehicle) \
        + calibration.nonlinear.static_deflection_m
    if sag == car.nonlinear.static_deflection_m:
        return car
    return dataclasses.replace(car, nonlinear=dataclasses.replace(
        car.nonlinear, static_deflection_m=sag))


@dataclass(frozen=True)
class SensorChannel:
    """One analogue channel: Gaussian noise then an ADC with ``bits`` over [min, max]."""

    # (each channel's own bounds: CHANNEL_LIMITS)
    noise_std: float = _nonneg()
    range_min: float = dataclasses.field(metadata={"positive": False})
    range_max: float = dataclasses.field(metadata={"positive": False})
    bits: int = dataclasses.field(metadata={"integer": True, "range": (2, 24)})

    @property
    def lsb(self) -> float:
        return (self.range_max - self.range_min) / (2**self.bits - 1)

    @property
    def variance(self) -> float:
        """One sample's noise variance, the ADC's quantisation (lsb^2 / 12) included."""
        return self.noise_std ** 2 + self.lsb ** 2 / 12.0


# each channel's physical bound on |range_min|, |range_max| (its unit) and the largest noise
# a sensor may have: a tenth of its span (a channel whose noise fills its range measures
# nothing)
CHANNEL_LIMITS = {"body_accel": 1000.0, "wheel_accel": 5000.0, "susp_defl": 1.0,
                  "motor_current": 5000.0, "speed": 200.0, "supply_voltage": 2000.0}
MAX_NOISE_SHARE = 0.1
# the bus voltage must oppose the back-EMF up to this suspension velocity (m/s): below it the
# bridge cannot drive the actuator at all (the default car: 48 V / 30 V s/m = 1.6 m/s)
MIN_CONTROLLABLE_MPS = 0.1

SENSOR_NAMES = ("body_accel", "wheel_accel", "susp_defl", "motor_current", "speed")
# every channel of [sensors]: the five above (sampled together, hil.sim.sensors.SensorSuite) and
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
    plant_dt_s: float = _pos(1e-5, 0.01)


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


def check_channel(path: Path, name: str, ch: SensorChannel) -> None:
    """A channel's cross-checks: its range ordered and within the quantity's physical bound
    (``CHANNEL_LIMITS``), its noise at most ``MAX_NOISE_SHARE`` of its span."""
    if ch.range_max <= ch.range_min:
        raise ConfigError(f"{path}: key 'sensors.{name}.range_max' must exceed range_min")
    limit = CHANNEL_LIMITS[name]
    for key in ("range_min", "range_max"):
        value = getattr(ch, key)
        if abs(value) > limit:
            raise ConfigError(f"{path}: key 'sensors.{name}.{key}' must be in [{-limit:g}, "
                              f"{limit:g}] (its physical range), got {value:g}")
    span = ch.range_max - ch.range_min
    if ch.noise_std > MAX_NOISE_SHARE * span:
        raise ConfigError(f"{path}: key 'sensors.{name}.noise_std' ({ch.noise_std:g}) must be "
                          f"at most {MAX_NOISE_SHARE:g} of the channel's span ({span:g})")


def check_actuator(path: Path, ap: ActuatorParams) -> None:
    """The actuator's cross-checks: a storage voltage within 10x the bus's, and a bus that
    opposes the back-EMF up to ``MIN_CONTROLLABLE_MPS``."""
    if ap.storage_voltage_v > 10 * ap.bus_voltage_v:
        raise ConfigError(f"{path}: key 'actuator.storage_voltage_v' is implausibly high")
    v = ap.bus_voltage_v / ap.force_constant_n_per_a
    if v < MIN_CONTROLLABLE_MPS:
        raise ConfigError(
            f"{path}: the bus voltage ({ap.bus_voltage_v:g} V) opposes the back-EMF "
            f"({ap.force_constant_n_per_a:.4g} V s/m) only up to {v:.3g} m/s of suspension "
            f"velocity (at least {MIN_CONTROLLABLE_MPS:g}): check actuator.bus_voltage_v, "
            f"screw_lead_m and torque_constant_nm_per_a")


def parse_vehicle(data: Mapping[str, Any], path: Path, base: VehicleConfig | None) -> VehicleConfig:
    """A vehicle file's table as a :class:`VehicleConfig`: ``[vehicle]`` with its five keys
    required; the other tables override ``base`` key by key (``base`` None: all required)."""
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
        check_channel(path, name, channel)
        channels[name] = channel
    check_actuator(path, actuator)
    return VehicleConfig(vehicle=vehicle, actuator=actuator, nonlinear=nonlinear,
                         sensors=SensorParams(**channels), sim=sim, source=str(path))
