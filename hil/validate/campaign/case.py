"""One case: its identity, the ``hil sim`` command that reproduces it, the software that
ran it, and its run and judgement (on a Dask worker)."""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import socket
import time
from pathlib import Path

from hil.config import PACKAGE_DIR
from hil.validate.acceptance import GRADE_ACCURACY, GRADE_MODE, RELATIVE_KEY, violations
from hil.validate.campaign.spec import base_spec, case_id, route_of, vehicle_config

MIXED = "mixed"            # a segment driven in more than one mode (case.driven_mode)
DRIVEN_SHARE = 0.95        # ... for less than this share of its window in its main mode


def command(case: dict, db_path: str = "DB") -> str:
    """The hil sim command that reproduces a case (vehicle variants and noise factors have no
    command-line form: ``hil campaign-case DB CASE_ID`` runs the case the database holds)."""
    parts = ["python -m hil sim", f"--route {case['route']['name']}",
             f"--mode {case['mode']}", f"--seed {case['seed']}"]
    v = case["vehicle"]
    shipped = PACKAGE_DIR / "vehicles" / f"{v['name']}.toml"
    if v["toml"]:
        if not (shipped.is_file() and shipped.read_text() == v["toml"]):
            return f"python -m hil campaign-case {db_path} {case_id(case)}"
        parts.append(f"--vehicle hil/vehicles/{v['name']}.toml")
    if "toml" in case["route"]:               # a route file: its text is in the case
        return f"python -m hil campaign-case {db_path} {case_id(case)}"
    if case["fixed_point"]:
        parts.append("--fixed-point")
    if case["duration_s"] is not None:
        parts.append(f"--duration {case['duration_s']:g}")
    if v["factors"] or v.get("nonlinear") or case["noise"] != 1.0:
        return f"python -m hil campaign-case {db_path} {case_id(case)}"
    return " ".join(parts + ["--key-file KEY"])


# what defines the program a case runs, beside its inputs: the packages' sources and data
SOURCE_PACKAGES = ("firmware", "calib", "hil")
SOURCE_SUFFIXES = (".py", ".toml", ".json")


@functools.lru_cache(maxsize=1)
def source_sha256() -> str:
    """SHA-256 over the source and data files of the firmware, calib and hil packages and the
    DBC, each by its path in the project: two processes with the same digest run the same
    program (the ``software_version`` of a case says which)."""
    import importlib

    from hil.transport.codec import DBC_PATH

    files = []
    for name in SOURCE_PACKAGES:
        base = Path(importlib.import_module(name).__file__).resolve().parent
        files += [(f"{name}/{f.relative_to(base).as_posix()}", f) for f in base.rglob("*")
                  if f.suffix in SOURCE_SUFFIXES and "__pycache__" not in f.parts
                  and f.is_file()]
    files.append(("dbc/" + DBC_PATH.name, DBC_PATH))
    h = hashlib.sha256()
    for rel, f in sorted(files):
        data = f.read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode())
        h.update(data)
    return h.hexdigest()


def software_version() -> str:
    """The ECU's software version (DID 0xF195) and the digest of the code that ran it:
    ``suspension-0.1.0+src.1a2b3c4d5e6f``."""
    from calib.ecu_params import SOFTWARE_VERSION

    return f"{SOFTWARE_VERSION}+src.{source_sha256()[:12]}"


# the SecOC key of every case: fixed (public, like the golden runs'), so a case's bytes are
# the same everywhere; the trace hash does not depend on it
CASE_KEY = bytes(range(16))


def calibration_key(case: dict) -> str:
    """What a case's calibration depends on (its calibration car and the sensor noise it is
    designed for), as text: the cases of one key drive with one design."""
    spec = case["vehicle"]
    nominal = spec.get("calibration") == "nominal"
    return json.dumps({"vehicle": base_spec(spec) if nominal else spec,
                       "noise": 1.0 if nominal else case["noise"]}, sort_keys=True)


def design(case: dict):
    """The calibration a case drives with (``firmware.params.EcuParams``), or the reason
    there is none (a str): computed once per ``calibration_key`` by the campaign's driver
    and carried to every case of that car, so every worker drives with the same bytes."""
    from hil.nodes import sil

    try:
        cfg = vehicle_config(case["vehicle"], case["noise"])
        return sil.ecu_params(calibration_car(case["vehicle"], cfg), case["mode"])
    except Exception as exc:  # noqa: BLE001 - the cases of this car record it
        return f"{type(exc).__name__}: {exc}"


def run_case(case: dict, acceptance: bool | str = True, params=None) -> dict:
    """Run one case (on a worker): the row of ``cases`` and the rows of ``segments``.
    ``params``: the calibration (``design``), else designed here. A case that raises is a
    result too (verdict ``error``, the exception in ``failed``): one bad case does not stop
    a campaign."""
    t0 = time.perf_counter()
    try:
        if isinstance(params, str):
            raise ValueError(params)
        return _run_case(case, acceptance, t0, params)
    except Exception as exc:  # noqa: BLE001 - recorded with the case
        return {"case_id": case_id(case), "case": case, "calibration_sha256": "",
                "design_sha256": "",
                "software_version": _version_or_blank(), "trace_sha256": "",
                "verdict": "error",
                "failed": [f"{type(exc).__name__}: {exc}"],
                "wall_s": time.perf_counter() - t0,
                "worker": f"{socket.gethostname()}:{os.getpid()}", "segments": []}


def _version_or_blank() -> str:
    try:
        return software_version()
    except Exception:  # noqa: BLE001 - an error row without a version rather than none
        return ""


def _run_case(case: dict, acceptance: bool | str, t0: float, params=None) -> dict:
    from calib.dataset import image_sha256
    from hil.nodes import sil

    cfg = vehicle_config(case["vehicle"], case["noise"])
    route = route_of(case["route"])
    if params is None:
        params = design(case)
        if isinstance(params, str):
            raise ValueError(params)
    report, _ = sil.run(cfg, route, case["mode"], case["seed"], params=params,
                        duration_s=case["duration_s"], fixed_point=case["fixed_point"],
                        key=CASE_KEY)
    failed = [c["name"] for c in report["checks"] if not c["ok"]]
    if report.get("dtcs_confirmed"):      # (which: a false DTC names a part)
        failed = [f"dtcs_confirmed ({', '.join(report['dtcs_confirmed'])})"
                  if f == "dtcs_confirmed" else f for f in failed]
    segments = []
    for i, (seg, rs) in enumerate(zip(report["segments"], route.segments)):
        row = judge_segment(cfg, route, rs, seg, case["mode"], acceptance,
                            scored_window(route, i, case["duration_s"]))
        row["idx"] = i
        if not row["ok"]:
            failed.append(f"segment {i + 1} ({seg['grade']}@{seg['speed_mps']:g}): "
                          f"{row['why']}")
        segments.append(row)
    return {"case_id": case_id(case), "case": case,
            "calibration_sha256": bytes(params.calibration_sha256).hex(),
            "design_sha256": image_sha256(params),
            "software_version": software_version(),
            "trace_sha256": report["trace_sha256"],
            "verdict": "fail" if failed else "pass", "failed": failed,
            "wall_s": time.perf_counter() - t0,
            "worker": f"{socket.gethostname()}:{os.getpid()}", "segments": segments}


def calibration_car(spec: dict, cfg):
    """The car the ECU is calibrated for: the case's own (``per-car``), or with a space's
    ``calibration = "nominal"`` its base car (the file's, the nominal sensors): one
    calibration shipped for every car the space holds."""
    if spec.get("calibration") != "nominal":
        return cfg
    return vehicle_config(base_spec(spec), 1.0)


def judge_segment(cfg, route, rs, seg: dict, mode: str, acceptance: bool | str,
                  window_s: float) -> dict:
    """A segment against the acceptance of the mode it was driven in (with any mode, the
    road grade estimated right for at least ``GRADE_ACCURACY`` of it), and its gap to the
    vehicle's own limit for that mode under the per-drive bound (``calib.linear.
    constrained_limits`` over the segment's scored ``window_s``: the best any causal
    controller reaches while each bounded ratio stays at most 1 on such a drive with 3 sigma
    confidence), the gap to the unbounded limit (``physical_limits``) beside it, and the
    scatter of one drive's value (``calib.linear.drive_scatter`` at the bounded limit's
    gain). The gap is judged on the mean over the seeds, in ``report``: one segment's ratio
    scatters around the mean by more than the gap a design is held to."""
    driven = driven_mode(seg, mode)
    row = {"grade": seg["grade"], "speed_mps": seg["speed_mps"], "mode": driven,
           "scored": bool(seg.get("scored", True)), "ratio": seg.get("ratio", {}),
           "limit_name": None, "limit_value": None, "gap": None, "limit_free": None,
           "gap_free": None, "sigma": None, "ok": True, "why": "", "metrics": seg}
    if not row["scored"]:
        return row
    grade_why = []
    accuracy = seg.get("grade_accuracy", 1.0)
    # (NaN: a grade beyond what the estimate names, E-H, is not scored: hil.nodes.sil)
    if acceptance and math.isfinite(accuracy) and accuracy < GRADE_ACCURACY:
        # the road grade the ECU estimates, right for this share of the segment at least
        grade_why = [f"grade_accuracy {accuracy:.3f} < {GRADE_ACCURACY:g}"]
        row["ok"], row["why"] = False, grade_why[0]
    if driven not in JUDGED:
        return row
    limits = _limits(cfg.vehicle, rs, route, window_s)
    r = seg["ratio"]
    name, key = JUDGED[driven]
    value = judged_value(driven, r)
    free, limit = limits[key]["free"], judged_limit(limits[key])
    row.update(limit_name=name, limit_value=limit, gap=value - limit, limit_free=free,
               gap_free=value - free, sigma=limits[key]["sigma"])
    why = []
    if acceptance:
        raised = (relative_raise(cfg.vehicle, rs, route, window_s, driven)
                  if acceptance == "relative" else None)
        why = violations(driven, r, limit, raised)
    why = grade_why + why
    row["ok"], row["why"] = not why, "; ".join(why)
    return row


def judged_limit(lim: dict) -> float:
    """The value of one of ``_limits``' entries a segment is judged by: the limit under the
    per-drive bound, else (a drive too short for any controller to hold the bound) the
    unbounded one."""
    return lim["free"] if lim["bounded"] is None else lim["bounded"]


def relative_raise(vehicle, rs, route, window_s: float, mode: str) -> dict:
    """The ``relative`` acceptance's move of ``mode``'s bound (``RELATIVE_KEY``; {} for a
    mode without one): the same margin above this vehicle's limit as above the default
    car's, both under the per-drive bound over ``window_s`` where both have one, else both
    unbounded. 0 for the default car itself (its limits are not computed for it)."""
    from hil.config import default_vehicle

    if mode not in RELATIVE_KEY:
        return {}
    base_vehicle = default_vehicle().vehicle
    if vehicle == base_vehicle:
        return {RELATIVE_KEY[mode]: 0.0}
    key = JUDGED[mode][1]
    own = _limits(vehicle, rs, route, window_s)[key]
    base = _limits(base_vehicle, rs, route, window_s)[key]
    which = "bounded" if own["bounded"] is not None and base["bounded"] is not None else "free"
    return {RELATIVE_KEY[mode]: own[which] - base[which]}


# per mode with a limit: the limit's name in the database and in calib.linear
JUDGED = {"comfort": ("comfort_ba", "comfort"), "safety": ("safety_dtd", "safety"),
          "comprehensive": ("eq43_sum", "eq43")}


def judged_ratio(mode: str) -> str:
    """What a segment driven in ``mode`` is judged by: the ratio its limit bounds, or "sum"
    (Eq. (43): the three), as ``calib.linear.LIMIT_VALUE`` says."""
    from calib.linear import LIMIT_VALUE
    from calib.model import OUTPUTS

    i = LIMIT_VALUE[JUDGED[mode][1]]
    return "sum" if i is None else OUTPUTS[i]


def judged_value(mode: str, ratio: dict) -> float:
    """The value of ``judged_ratio(mode)`` in a segment's ratios."""
    what = judged_ratio(mode)
    return sum(ratio.values()) if what == "sum" else ratio[what]


def scored_window(route, i: int, duration_s) -> float:
    """The seconds of segment ``i`` a run scores: what it drove of the segment (all of it, or
    up to the case's ``duration_s``) after the settling window (``hil.nodes.sil``)."""
    from hil.nodes.sil import SETTLE_S

    start = sum(s.duration_s() for s in route.segments[:i])
    driven = route.segments[i].duration_s()
    if duration_s is not None:
        driven = min(driven, max(0.0, duration_s - start))
    return driven - SETTLE_S


def driven_mode(seg: dict, mode: str) -> str:
    """The mode a segment was driven in: the active mode of at least ``DRIVEN_SHARE`` of its
    scored window, else ``MIXED``: the road-holding override took over for a longer part of
    it (safety first, ``road_holding_share``), or the driver's mode changed inside it. A
    mixed window's ratios belong to no mode, so no mode's acceptance or limit judges them;
    the report counts them. (A few per cent in another mode are judged with the window's
    mode: the override's safety mode has a higher BA ratio and Eq. (43) sum than comfort and
    comprehensive, so that judgement errs on the strict side.)"""
    modes = seg.get("modes")
    if not modes:                     # (not scored)
        return GRADE_MODE.get(seg["grade"], mode) if mode == "auto" else mode
    top, share = max(modes.items(), key=lambda kv: kv[1])
    return top if share >= DRIVEN_SHARE else MIXED


# the road a limit is computed on: any (the limits and the scatter are ratios to the passive
# car on the same road, independent of the road's roughness in a linear model); one fixed
# value, so a limit's bits do not depend on which segment asked first
_LIMIT_GQ_M3 = 64e-6


def _limits(vehicle, rs, route, window_s: float) -> dict:
    """The limits of a vehicle at a route segment's speed, each as {"free": the unbounded
    limit, "bounded": under the per-drive bound over ``window_s``, "sigma": one drive's
    scatter of the bounded value}."""
    return _limit_values(vehicle, rs.speed_mps, route.road.convention,
                         route.road.cutoff_n_per_m, round(window_s, 6))


@functools.lru_cache(maxsize=64)
def _limit_values(vehicle, speed: float, convention: str, cutoff: float, window_s: float
                  ) -> dict:
    """The limits' values, kept in the design cache (``calib.cache``: keyed by the vehicle,
    the speed, the window and the design code; shared by a campaign's workers, which would
    otherwise each solve them for every vehicle: a few seconds of Riccati solves per speed,
    more than a case's drive)."""
    import pickle

    from calib import cache
    from calib.linear import constrained_limits, drive_scatter, physical_limits
    from calib.model import linear_model

    def compute() -> dict:
        model = linear_model(vehicle, _LIMIT_GQ_M3, speed, convention, cutoff)
        free = physical_limits(model)
        try:
            bounded = constrained_limits(model, window_s)
        except ValueError:              # (a drive too short for the per-drive bound)
            return {name: {"free": free[name].value, "bounded": None, "sigma": None}
                    for _, name in JUDGED.values()}
        return {name: {"free": free[name].value, "bounded": res.value,
                       "sigma": drive_scatter(model, name, res.K, window_s)}
                for name, res in bounded.items()}
    parts = (pickle.dumps(vehicle, protocol=5),
             repr((speed, convention, cutoff, window_s)).encode())
    return cache.cached("limits", parts, compute)
