"""The ride verdict of one drive (``hil sim``, ``hil run``): every scored segment against the
SIL acceptance of the mode it was driven in (``hil.validate.acceptance``: its ratios to the
passive twin on the same road within the mode's bounds), as a campaign judges its cases
(``hil.validate.campaign.case.judge_segment``), with one difference a drive of any length
needs: each bound is widened by the scatter a shorter window adds.

The designs hold their bounds with ``ratio_window_z`` sigma confidence on a drive of
``ratio_window_s`` (180 s, ``calib.options``: the ratio measured over such a window scatters
by sigma_D around the law's exact ratio, ``calib.model.window_scatter``), and a campaign's
segments are that long: its bounds are the acceptance's own. Over a window of T seconds the
log of a ratio scatters by sigma_T >= sigma_D; a drive is judged against
bound x exp(z (sigma_T - sigma_D)): a design that keeps its margin fails a drive by chance
with probability at most Phi(-z) per ratio (0.13 % at z = 3), whatever the drive's length.
sigma is the law's (the mode's designed state feedback: the comfort mode's BP-PID runs
around it) at the segment's speed; at 180 s the widening is 0. The sum of Eq. (43) scatters
relatively at most as much as its most scattered ratio, so its bound takes that one's.

A car other than the default one is judged as a campaign's ``relative`` acceptance does:
the comfort BA and safety DTD bounds move by the gap between the car's own limit and the
default car's, each under the per-drive bound over ``ratio_window_s`` (the campaign's
``relative_raise`` over the window the designs hold their bounds over; this drive's own
length is in the widening). The Eq. (43) sum is over the
car's own limit, the same way.

A segment driven in energy feedback, passive, or in more than one mode (``driven_mode``) has
no ride bound: its row says so and no check is made. Faults injected into a run (``hil run
--inject``) leave the ride unjudged: the fault campaign judges those runs."""

from __future__ import annotations

import math

import numpy as np

from hil.report import verdict
from hil.validate.acceptance import ACCEPTANCE

RATIOS = ("ba", "sws", "dtd")
# the designed state feedback each judged mode drives (firmware.params.ControlParams)
LAW = {"comfort": "k_comfort", "safety": "k_safety", "comprehensive": "k_comprehensive"}


def attach(report: dict, cfg, route, params, opts=None) -> dict:
    """Judge ``report``'s segments (``judge``), put the rows in ``report["ride"]``, add one
    check per judged segment to its checks and attach the verdict again. Returns it."""
    rows = judge(report, cfg, route, params, opts)
    report["ride"] = rows
    checks = [verdict.Check(**c) for c in report.get("checks", [])]
    checks += [verdict.Check(r["check"], r["worst"], "<= 1", r["ok"])
               for r in rows if r["judged"]]
    verdict.attach(report, checks)
    return report


def judge(report: dict, cfg, route, params, opts=None) -> list[dict]:
    """One row per segment of the drive: ``judged`` (False with ``why`` where the segment has
    no ride bound), else each bound as {got, bound, widened, limit} in ``bounds``, ``worst``
    (the largest got / limit: at most 1 passes) and ``ok``."""
    from calib.options import DesignOptions
    from hil.validate.campaign.case import JUDGED, driven_mode, scored_window

    opts = opts or DesignOptions()
    rows = []
    for i, (seg, rs) in enumerate(zip(report["segments"], route.segments)):
        row = {"segment": i + 1, "grade": seg["grade"], "speed_mps": seg["speed_mps"],
               "judged": False}
        rows.append(row)
        if not seg.get("scored", True):
            row["why"] = "not scored (no longer than the settling window)"
            continue
        driven = driven_mode(seg, report["mode"])
        row["mode"] = driven
        if driven not in JUDGED:
            row["why"] = f"driven in {driven}: no ride bound"
            continue
        window = scored_window(route, i, report["duration_s"])
        row.update(judged=True, check=f"ride.segment{i + 1}.{driven}", window_s=window,
                   bounds=_bounds(cfg, route, rs, driven, seg["ratio"], window, params, opts))
        row["worst"] = max(b["got"] / b["limit"] for b in row["bounds"].values())
        row["ok"] = bool(row["worst"] <= 1.0)
    return rows


def _bounds(cfg, route, rs, mode: str, ratio: dict, window: float, params, opts) -> dict:
    from calib.model import linear_model, window_scatter
    from hil.validate.campaign.case import _LIMIT_GQ_M3, _limits, judged_limit, relative_raise

    # (the ratios and their scatter do not depend on the road's roughness: the campaign's)
    model = linear_model(cfg.vehicle, _LIMIT_GQ_M3, rs.speed_mps, route.road.convention,
                         route.road.cutoff_n_per_m)
    K = np.asarray(getattr(params.control, LAW[mode]), dtype=float)
    s_t = window_scatter(model, K, window)[1]
    s_d = window_scatter(model, K, opts.ratio_window_s)[1]
    extra = {k: opts.ratio_window_z * max(0.0, float(a - b))
             for k, a, b in zip(RATIOS, s_t, s_d)}
    raised = relative_raise(cfg.vehicle, rs, route, opts.ratio_window_s, mode)
    out = {}
    for key, bound in ACCEPTANCE[mode].items():
        if key == "max":                          # every ratio at most the bound
            for k in RATIOS:
                out[k] = _one(ratio[k], bound, extra[k])
        elif key == "sum_eq43":                   # the sum over the car's own Eq. (43) limit
            eq43 = judged_limit(_limits(cfg.vehicle, rs, route, opts.ratio_window_s)["eq43"])
            out[key] = _one(sum(ratio[k] for k in RATIOS) / eq43, bound, max(extra.values()))
        else:
            out[key] = _one(ratio[key], bound + raised.get(key, 0.0), extra[key])
    return out


def _one(got: float, bound: float, widen: float) -> dict:
    limit = bound * math.exp(widen)
    return {"got": float(got), "bound": float(bound), "widened": float(limit - bound),
            "limit": float(limit)}


def judge_run(report: dict, cfg, route, args) -> None:
    """``attach`` for ``hil run`` (``hil.bench.supervisor.run``'s judge) with the ECU node's
    calibration, built again from the design cache: the car of ``--calibration``, else the
    driven one, with ``--design`` and ``--gains``."""
    from pathlib import Path

    from hil.cli import cars_or_exit, design_or_exit
    from hil.nodes import sil

    _, cal = cars_or_exit(args.vehicle, args.calibration)
    opts = design_or_exit(args.design)
    params = sil.ecu_params(cal, args.mode, opts=opts,
                            gains_file=Path(args.gains) if args.gains else None)
    attach(report, cfg, route, params, opts)
