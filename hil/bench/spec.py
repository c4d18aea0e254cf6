"""What a bench run is: one typed specification that ``hil run``'s command line, the fault
campaign and any other caller build, and the supervisor reads (``hil.bench.supervisor.run``).
Its defaults are the command line's."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Optional

from hil.report.verdict import Limits


@dataclass
class RunSpec:
    """One ``hil run``: the inputs (route, car, mode, seed), how the ECU runs (controller,
    gains, design, arithmetic), the driver, the bus and its pace, the outputs and the verdict's
    limits. ``pace`` None: realtime for a person at the web page (``driver = "web"``), else
    lockstep. ``inject`` and ``outside_frames`` are the fault campaign's: the injector's plan
    file, and the frames outside clients put on the bus (counted by them while the run goes
    on, so that the log's check of frames against senders counts them too)."""

    route: str = "full_road_section"
    mode: str = "auto"
    seed: int = 1
    vehicle: Optional[str] = None
    calibration: Optional[str] = None          # the car the ECU is calibrated for
    controller: Optional[str] = None
    gains: Optional[str] = None
    design: Optional[str] = None
    duration: Optional[float] = None
    fixed_point: bool = False
    driver: Optional[str] = None
    script: Optional[str] = None
    web_port: int = 0
    interface: Optional[str] = None
    channel: Optional[str] = None
    pace: Optional[str] = None
    rt_priority: Optional[int] = None
    allow_external_tx: bool = False
    stall_s: Optional[float] = None
    key_file: Optional[str] = None
    out: str = "out/run"
    start_time: Optional[str] = None
    log_format: Optional[list[str]] = None
    json: bool = False
    junit: Optional[str] = None
    max_missed_ratio: float = Limits().max_missed_ratio
    max_lost_ratio: float = Limits().max_lost_ratio
    inject: Optional[str] = None
    outside_frames: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_args(cls, args: Any) -> "RunSpec":
        """The specification of ``hil run``'s parsed command line (its other options, such as
        ``--no-cache``, act before the run and are not part of it)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in vars(args).items() if k in names})
