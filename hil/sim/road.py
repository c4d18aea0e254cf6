"""ISO 8608 random road profiles as a function of distance, and routes of segments.

The paper's Eq. (1) is a first-order filter on white noise at constant speed. A road is a
function of distance (errata 4), so the profile is generated in distance::

    dz/dx = -2*pi*n_c*z + 2*pi*n0*sqrt(kappa*G_q(x)) * w(x)

with ``w`` unit white noise in distance, ``n0 = 0.1 1/m`` and the spatial lower cut-off ``n_c``
(default 0.005 1/m, which is the paper's f0 = 0.1 Hz at its v0 = 20 m/s). Driven at a constant
speed v this is exactly Eq. (1) with f0 = n_c*v. ``kappa`` is the PSD convention (errata 5):
``iso`` (kappa = 1/2, a profile whose one-sided displacement PSD at n0 equals G_q, the ISO 8608
definition) or ``paper`` (kappa = 1, Eq. (1) literally, every RMS sqrt(2) higher).

The process is sampled on a fixed distance grid with its exact Ornstein-Uhlenbeck transition
(no discretisation error at the grid points) and linearly interpolated between them, so the same
seed gives the same road at any speed. G_q may change from segment to segment; the profile stays
continuous across segment boundaries because it is one process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from calib.errors import ConfigError, read_toml
from hil.config import PACKAGE_DIR
from hil.kernels.road import ar1

from calib.iso8608 import (CONVENTIONS, DEFAULT_CUTOFF_N_PER_M, GRADE_GQ_M3, GRADES, N0_PER_M,  # noqa: F401
                           convention_factor, gq_of, grade_of, road_noise_gain)

DEFAULT_DX_M = 0.01
# bounds that keep a route's memory and numbers sane, checked before anything is allocated
MIN_DX_M = 1e-3                # road grid: 1 mm .. 0.1 m
MIN_CUTOFF_N_PER_M = 1e-3      # the OU road's cut-off wavenumber: 1e-3 .. n0 (1/m)
GQ_RANGE_M3 = (1e-9, 1e-1)     # G_q(n0): ISO 8608 A is 1.6e-5, H 1.6e-2
MAX_ROUTE_S = 1800.0           # a route drives at most 30 min (1.8 M plant ticks)
MAX_ROAD_SAMPLES = 20_000_000  # road grid points (160 MB of heights)
MAX_SPEED_MPS = 70.0     # the DBC's declared range of VEHICLE_SPEED.SPEED (252 km/h)
ROUTES_DIR = PACKAGE_DIR / "routes"


@dataclass(frozen=True)
class Segment:
    gq_m3: float
    length_m: float
    speed_mps: float
    grade: str  # the ISO label: given, or the band that contains gq_m3

    def duration_s(self) -> float:
        return self.length_m / self.speed_mps


@dataclass(frozen=True)
class RoadSettings:
    convention: str = "iso"
    cutoff_n_per_m: float = DEFAULT_CUTOFF_N_PER_M
    dx_m: float = DEFAULT_DX_M


@dataclass(frozen=True)
class Route:
    name: str
    segments: tuple[Segment, ...]
    road: RoadSettings = field(default_factory=RoadSettings)
    description: str = ""

    @property
    def length_m(self) -> float:
        return sum(s.length_m for s in self.segments)

    @property
    def duration_s(self) -> float:
        return sum(s.duration_s() for s in self.segments)

    def boundaries_m(self) -> np.ndarray:
        """Start distance of each segment, followed by the route's end."""
        return np.concatenate([[0.0], np.cumsum([s.length_m for s in self.segments])])

    def with_convention(self, convention: str | None) -> "Route":
        if convention is None:
            return self
        convention_factor(convention)
        road = RoadSettings(convention, self.road.cutoff_n_per_m, self.road.dx_m)
        return Route(self.name, self.segments, road, self.description)


def make_segment(grade: str | None = None, *, gq_m3: float | None = None, length_m: float,
                 speed_mps: float) -> Segment:
    if (grade is None) == (gq_m3 is None):
        raise ValueError("a segment needs exactly one of grade and gq_m3")
    if grade is not None:
        gq_m3 = gq_of(grade)
        label = grade.upper()
    else:
        if not (math.isfinite(gq_m3) and gq_m3 > 0):
            raise ValueError(f"gq_m3 must be positive and finite, got {gq_m3}")
        label = grade_of(gq_m3)
    for name, value in (("length_m", length_m), ("speed_mps", speed_mps)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be positive and finite, got {value}")
    if speed_mps > MAX_SPEED_MPS:
        raise ValueError(f"speed_mps must be at most {MAX_SPEED_MPS:g} m/s (the declared range "
                         f"of VEHICLE_SPEED.SPEED), got {speed_mps}")
    return Segment(float(gq_m3), float(length_m), float(speed_mps), label)


def constant_route(grade: str, speed_mps: float, duration_s: float, convention: str = "iso",
                   cutoff_n_per_m: float = DEFAULT_CUTOFF_N_PER_M) -> Route:
    """One segment of one grade at one speed, lasting ``duration_s``."""
    convention_factor(convention)
    seg = make_segment(grade, length_m=speed_mps * duration_s, speed_mps=speed_mps)
    return Route(f"{grade}@{speed_mps:g}", (seg,),
                 RoadSettings(convention=convention, cutoff_n_per_m=cutoff_n_per_m))


# -- route files -----------------------------------------------------------------------------

_SEGMENT_KEYS = {"grade", "gq_m3", "length_m", "speed_mps"}
_ROAD_KEYS = {"convention", "cutoff_n_per_m", "dx_m"}
_TOP_KEYS = {"name", "description", "road", "segment"}


def _num(path: Path, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{path}: key '{key}' must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ConfigError(f"{path}: key '{key}' must be positive and finite, got {value}")
    return value


def parse_route(data: Mapping[str, Any], path: Path, name: str) -> Route:
    for key in data:
        if key not in _TOP_KEYS:
            raise ConfigError(f"{path}: unknown key '{key}' (known: {', '.join(sorted(_TOP_KEYS))})")
    road_table = data.get("road", {})
    if not isinstance(road_table, Mapping):
        raise ConfigError(f"{path}: 'road' must be a table")
    for key in road_table:
        if key not in _ROAD_KEYS:
            raise ConfigError(f"{path}: unknown key 'road.{key}' (known: {', '.join(sorted(_ROAD_KEYS))})")
    convention = road_table.get("convention", "iso")
    if convention not in CONVENTIONS:
        raise ConfigError(f"{path}: key 'road.convention' must be 'iso' or 'paper', got {convention!r}")
    cutoff = _num(path, "road.cutoff_n_per_m", road_table.get("cutoff_n_per_m", DEFAULT_CUTOFF_N_PER_M))
    dx = _num(path, "road.dx_m", road_table.get("dx_m", DEFAULT_DX_M))
    if not MIN_DX_M <= dx <= 0.1:
        raise ConfigError(f"{path}: key 'road.dx_m' must be in [{MIN_DX_M:g}, 0.1] m, got {dx}")
    if not MIN_CUTOFF_N_PER_M <= cutoff < N0_PER_M:
        raise ConfigError(f"{path}: key 'road.cutoff_n_per_m' must be in "
                          f"[{MIN_CUTOFF_N_PER_M:g}, n0 = 0.1) 1/m, got {cutoff}")
    raw_segments = data.get("segment")
    if not isinstance(raw_segments, list) or not raw_segments:
        raise ConfigError(f"{path}: missing '[[segment]]' entries (at least one is needed)")
    segments = []
    for i, seg in enumerate(raw_segments):
        where = f"segment[{i}]"
        if not isinstance(seg, Mapping):
            raise ConfigError(f"{path}: '{where}' must be a table")
        for key in seg:
            if key not in _SEGMENT_KEYS:
                raise ConfigError(f"{path}: unknown key '{where}.{key}' (known: {', '.join(sorted(_SEGMENT_KEYS))})")
        for key in ("length_m", "speed_mps"):
            if key not in seg:
                raise ConfigError(f"{path}: missing key '{where}.{key}'")
        if ("grade" in seg) == ("gq_m3" in seg):
            raise ConfigError(f"{path}: '{where}' needs exactly one of 'grade' and 'gq_m3'")
        length = _num(path, f"{where}.length_m", seg["length_m"])
        speed = _num(path, f"{where}.speed_mps", seg["speed_mps"])
        if speed > MAX_SPEED_MPS:
            raise ConfigError(f"{path}: key '{where}.speed_mps' must be at most "
                              f"{MAX_SPEED_MPS:g} (VEHICLE_SPEED.SPEED's range), got {speed}")
        if "grade" in seg:
            grade = seg["grade"]
            if not isinstance(grade, str) or grade.upper() not in GRADE_GQ_M3 or len(grade) != 1:
                raise ConfigError(f"{path}: key '{where}.grade' must be one of {', '.join(GRADES)}, got {grade!r}")
            segments.append(make_segment(grade, length_m=length, speed_mps=speed))
        else:
            gq = _num(path, f"{where}.gq_m3", seg["gq_m3"])
            if not GQ_RANGE_M3[0] <= gq <= GQ_RANGE_M3[1]:
                raise ConfigError(f"{path}: key '{where}.gq_m3' must be in [{GQ_RANGE_M3[0]:g}, "
                                  f"{GQ_RANGE_M3[1]:g}] m^3, got {gq}")
            segments.append(make_segment(gq_m3=gq, length_m=length, speed_mps=speed))
    duration = sum(s.duration_s() for s in segments)
    if duration > MAX_ROUTE_S:
        raise ConfigError(f"{path}: the route drives {duration:.4g} s; at most {MAX_ROUTE_S:g} s "
                          f"(split it into several runs)")
    samples = (sum(s.length_m for s in segments) + 1.0) / dx
    if samples > MAX_ROAD_SAMPLES:
        raise ConfigError(f"{path}: the road grid would hold {samples:.3g} points (length / "
                          f"road.dx_m); at most {MAX_ROAD_SAMPLES:.3g}: raise dx_m or shorten it")
    for key in ("name", "description"):
        if key in data and not isinstance(data[key], str):
            raise ConfigError(f"{path}: key '{key}' must be a string")
    return Route(name=data.get("name", name), segments=tuple(segments),
                 road=RoadSettings(convention, cutoff, dx), description=data.get("description", ""))


def shipped_routes() -> list[str]:
    return sorted(p.stem for p in ROUTES_DIR.glob("*.toml"))


def load_route(spec: str | Path) -> Route:
    """A route from a TOML file path, or by the name of a shipped route."""
    path = Path(spec)
    if not path.exists() and str(spec) in shipped_routes():
        path = ROUTES_DIR / f"{spec}.toml"
    elif not path.exists() and path.suffix != ".toml" and "/" not in str(spec):
        raise ConfigError(f"{spec}: no such route file or shipped route (shipped: {', '.join(shipped_routes())})")
    return parse_route(read_toml(path, "route"), path, path.stem)


# -- profile generation ----------------------------------------------------------------------

@dataclass(frozen=True)
class RoadProfile:
    """Road height on a uniform distance grid ``x = i*dx``; linear between grid points."""

    dx_m: float
    heights_m: np.ndarray
    route: Route
    seed: int

    @property
    def length_m(self) -> float:
        return (len(self.heights_m) - 1) * self.dx_m

    def height_at(self, x_m: np.ndarray | float) -> np.ndarray | float:
        return np.interp(x_m, np.arange(len(self.heights_m)) * self.dx_m, self.heights_m)


def generate_profile(route: Route, seed: int) -> RoadProfile:
    """Exact OU sampling on the distance grid, seeded by ``numpy.random.default_rng(seed)``."""
    dx = route.road.dx_m
    lam = 2.0 * math.pi * route.road.cutoff_n_per_m
    kappa = convention_factor(route.road.convention)
    n = int(math.ceil((route.length_m + 1.0) / dx)) + 1  # 1 m margin past the end
    x = np.arange(n) * dx
    seg_index = np.searchsorted(route.boundaries_m()[1:-1], x, side="right")
    gq = np.array([s.gq_m3 for s in route.segments])[seg_index]
    a2 = (2.0 * math.pi * N0_PER_M) ** 2 * kappa * gq          # slope-noise intensity
    phi = math.exp(-lam * dx)
    step_std = np.sqrt(a2 * (1.0 - phi * phi) / (2.0 * lam))
    stationary_std = math.sqrt(a2[0] / (2.0 * lam))
    rng = np.random.default_rng(seed)
    xi = rng.standard_normal(n)
    drive = step_std * xi
    drive[0] = stationary_std * xi[0]
    heights = ar1(drive, phi)
    return RoadProfile(dx, heights, route, seed)


def psd_estimate(profile: RoadProfile, segment_m: float = 200.0) -> tuple[np.ndarray, np.ndarray]:
    """One-sided displacement PSD G_d(n) (m^3) of a profile by Welch's method."""
    from scipy.signal import welch

    nper = int(segment_m / profile.dx_m)
    return welch(profile.heights_m, fs=1.0 / profile.dx_m, nperseg=nper, detrend="linear")


def estimate_gq(profile: RoadProfile, band: Sequence[float] = (0.05, 0.2)) -> float:
    """G_q(n0) estimated from the Welch PSD over a band around n0, undoing the n^-2 shape
    (with the cut-off) of the model: mean of G_d(n) (n^2 + n_c^2) / n0^2."""
    n, g = psd_estimate(profile)
    sel = (n >= band[0]) & (n <= band[1])
    nc = profile.route.road.cutoff_n_per_m
    return float(np.mean(g[sel] * (n[sel] ** 2 + nc**2) / N0_PER_M**2))


@dataclass(frozen=True)
class Timeline:
    """Where the car is at each plant tick: position, speed and segment index."""

    dt_s: float
    x_m: np.ndarray
    speed_mps: np.ndarray
    segment: np.ndarray

    def __len__(self) -> int:
        return len(self.x_m)


def drive_timeline(route: Route, dt_s: float) -> Timeline:
    """Tick positions of a drive along the route: constant speed within a segment, the speed
    of the segment the car is in at the start of each tick. Ends when the route ends."""
    bounds = route.boundaries_m()
    xs, vs, segs = [], [], []
    x = 0.0
    for i, seg in enumerate(route.segments):
        end = bounds[i + 1]
        # ticks whose start position lies in this segment
        k = max(0, int(math.ceil((end - x) / (seg.speed_mps * dt_s) - 1e-9)))
        pos = x + np.arange(k) * seg.speed_mps * dt_s
        xs.append(pos)
        vs.append(np.full(k, seg.speed_mps))
        segs.append(np.full(k, i, dtype=np.int32))
        x = x + k * seg.speed_mps * dt_s
    return Timeline(dt_s, np.concatenate(xs), np.concatenate(vs), np.concatenate(segs))
