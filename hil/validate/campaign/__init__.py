"""Validation campaigns: a matrix of SIL cases (routes x seeds x vehicles x modes x arithmetic
x sensor noise) run on Dask, each judged, the results in SQLite.

    python -m hil campaign FILE.toml [--scheduler local|tcp://HOST:PORT] [--workers N]
                                     [--out DIR] [--json]
    python -m hil campaign-report DIR/campaign.sqlite [--out DIR] [--json]

A case is one ``hil sim`` run, deterministic: the same case gives the same ``trace_sha256``
on any worker and as the plain ``hil sim`` command stored with it. Workers get the project's
code from the installed package and the vehicle and route files as text inside the case (no
shared disk). Results go to ``DIR/campaign.sqlite`` (schema: ``SCHEMA``) as each case ends;
a case already there is not run again (resumable; Ctrl-C keeps what finished).

The campaign file (every key but ``routes`` optional)::

    [campaign]
    name = "family"
    routes = ["full_road_section"]          # shipped names or route files
    seeds = [1, 2, 3]                       # or {from = 1, to = 10}
    modes = ["auto"]
    fixed_point = [false]                   # [false, true]: both arithmetic paths
    noise = [1.0]                           # factors on every sensor's noise
    duration_s = 60                         # stop each run early (default: the whole route)

    [[vehicle]]                             # none: the default car
    file = "hil/vehicles/suv.toml"          # omit for the default car
    sprung_mass_kg = [0.8, 1.0, 1.2]        # variants: factors on keys of [vehicle]

    [nonlinear]                             # every vehicle's [nonlinear] keys set to these
    bump_stops = true                       # (a vehicle file's own table, then this one)

    [criteria]
    acceptance = true                       # the firmware issue's SIL acceptance per segment;
                                            # "relative": BA, DTD bounds moved by the
                                            # vehicle's limit minus the default car's
    max_gap = 0.03                          # each mean ratio at most this above its limit
"""

from hil.validate.campaign.case import (DRIVEN_SHARE, MIXED, calibration_key, command, design,
                                        driven_mode, judge_segment, run_case, software_version,
                                        source_sha256)
from hil.validate.campaign.cli import case_main, main, report_main
from hil.validate.campaign.cluster import SeparateCluster, run
from hil.validate.campaign.report import render, report, report_figure
from hil.validate.campaign.spec import Campaign, case_id, load, route_of, vehicle_config
from hil.validate.campaign.store import SCHEMA, done_ids, open_db, store

__all__ = ["Campaign", "DRIVEN_SHARE", "MIXED", "SCHEMA", "SeparateCluster", "calibration_key",
           "case_id", "case_main", "command", "design", "done_ids", "driven_mode",
           "judge_segment", "load", "main",
           "open_db", "render", "report", "report_figure", "report_main", "route_of", "run",
           "run_case", "software_version", "source_sha256", "store", "vehicle_config"]
