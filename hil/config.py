"""The bench's files: vehicle files (``hil/vehicles/``, the paper's Table 3 car by default; their
types and parsing are ``calib.vehicle``'s), the run modes and controllers by name, and driver
scripts. Every problem with a file raises :class:`ConfigError`, whose message is one line
naming the file and the key; CLIs turn it into that line on stderr and exit code 2.
"""

from __future__ import annotations

from pathlib import Path

from calib.errors import ConfigError, read_toml
from calib.vehicle import VehicleConfig, check_number, parse_vehicle
from firmware.params import CTRL_NAMES, MODE_ENERGY, MODE_NAMES

PACKAGE_DIR = Path(__file__).resolve().parent
DEFAULT_VEHICLE_FILE = PACKAGE_DIR / "vehicles" / "table3.toml"


_DEFAULT: VehicleConfig | None = None


def default_vehicle() -> VehicleConfig:
    """The paper's Table 3 car with the project's default actuator and sensors."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = parse_vehicle(read_toml(DEFAULT_VEHICLE_FILE, "vehicle"),
                                 DEFAULT_VEHICLE_FILE, None)
    return _DEFAULT


def load_vehicle(path: str | Path | None) -> VehicleConfig:
    """Load a vehicle file. ``[vehicle]`` is required with all five keys; the other tables
    override the defaults key by key. ``None`` gives the default car."""
    if path is None:
        return default_vehicle()
    path = Path(path)
    cfg = parse_vehicle(read_toml(path, "vehicle"), path, default_vehicle())
    from calib.model import check_plausible     # (scipy: only when a file is read)

    check_plausible(cfg, path)
    return cfg


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
        t = check_number(path, f"{key}.t_s", r["t_s"], positive=True, allow_zero=True)
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
