"""Drive a plant along a route: the time loop shared by the tools and the tests.

The road height at each tick comes from the distance-domain profile at the car's position, so
a route with several speeds sees one continuous road.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from calib.vehicle import VehicleConfig
from hil.sim.metrics import RideMetrics, ride_metrics
from hil.sim.plant import QuarterCarPlant
from hil.sim.road import RoadProfile, Route, Timeline, drive_timeline, generate_profile

# controller(tick, plant) -> (duty, regen, enable)
Controller = Callable[[int, QuarterCarPlant], tuple[float, bool, bool]]


@dataclass
class DriveTrace:
    """Per-tick record of a drive (values at the end of each tick)."""

    dt_s: float
    timeline: Timeline
    zf_m: np.ndarray
    ba_mps2: np.ndarray
    wheel_accel_mps2: np.ndarray
    sws_m: np.ndarray
    dtd_m: np.ndarray
    force_n: np.ndarray
    current_a: np.ndarray
    bump_contact: np.ndarray
    lift_off: np.ndarray
    plant: QuarterCarPlant

    def metrics(self, sel: slice | np.ndarray = slice(None)) -> RideMetrics:
        return ride_metrics(self.ba_mps2[sel], self.sws_m[sel], self.dtd_m[sel],
                            self.force_n[sel], 1.0 / self.dt_s, self.bump_contact[sel],
                            self.lift_off[sel])


def road_at_ticks(profile: RoadProfile, timeline: Timeline) -> np.ndarray:
    """Road height at the start of every tick and at the end of the last one."""
    x_end = timeline.x_m[-1] + timeline.speed_mps[-1] * timeline.dt_s
    return np.asarray(profile.height_at(np.append(timeline.x_m, x_end)))


def drive(cfg: VehicleConfig, route: Route, seed: int, *, actuator: bool = False,
          controller: Optional[Controller] = None, ledger: bool = False,
          progress: Optional[Callable[[int, int], None]] = None) -> DriveTrace:
    """Simulate the car over ``route`` with the road of ``seed``. Without a controller the
    actuator (if fitted) has its bridge disabled."""
    dt = cfg.sim.plant_dt_s
    timeline = drive_timeline(route, dt)
    profile = generate_profile(route, seed)
    zf = road_at_ticks(profile, timeline)
    plant = QuarterCarPlant(cfg, actuator=actuator, ledger=ledger)
    plant.reset(zf[0])
    n = len(timeline)
    out = {name: np.empty(n) for name in ("ba", "wa", "sws", "dtd", "force", "current")}
    contact = np.zeros(n, dtype=bool)
    lifted = np.zeros(n, dtype=bool)
    ba, wa, sws, dtd, force, current = (out[k] for k in ("ba", "wa", "sws", "dtd", "force", "current"))
    report_every = max(1, n // 100)
    for k in range(n):
        if controller is not None:
            duty, regen, enable = controller(k, plant)
            plant.step(zf[k + 1], duty, regen, enable)
        else:
            plant.step(zf[k + 1], 0.0, False, False)
        ba[k], wa[k] = plant.accelerations()
        sws[k] = plant.x[2] - plant.x[3]
        dtd[k] = plant.x[3] - plant.zf
        force[k] = plant.actuator_force_n()
        current[k] = plant.x[4]
        contact[k] = plant.in_bump_contact
        lifted[k] = plant.tire_lifted
        if progress is not None and (k % report_every == 0 or k == n - 1):
            progress(k + 1, n)
    return DriveTrace(dt, timeline, zf[1:], ba, wa, sws, dtd, force, current, contact, lifted, plant)


def segment_masks(trace: DriveTrace, settle_s: float = 0.0) -> list[np.ndarray]:
    """Per segment, the ticks that lie in it after ``settle_s`` seconds in the segment."""
    seg = trace.timeline.segment
    masks = []
    for i in range(int(seg.max()) + 1 if len(seg) else 0):
        idx = np.flatnonzero(seg == i)
        skip = int(round(settle_s / trace.dt_s))
        mask = np.zeros(len(seg), dtype=bool)
        mask[idx[skip:]] = True
        masks.append(mask)
    return masks
