"""Software-in-the-loop: the ECU, plant and driver-app nodes (``hil.nodes``) in one process,
exchanging DBC-encoded frames through a FIFO that stands in for the bus, with the lockstep
protocol of ``hil run``. A passive twin rides the same road inside the plant node.

``trace_sha256`` hashes every input and output of the ECU, so a seed and a configuration pin
the run to the byte, and ``hil run --pace lockstep`` over a real bus must give the same hash.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from calib.ecu_params import build, with_controllers
from calib.options import DesignOptions
from calib.vehicle import VehicleConfig
from firmware import params as fp
from firmware import safety
from firmware.modes import REASON_ROAD_HOLDING
from hil.config import CONTROLLERS, RUN_MODES as MODES, ConfigError
from hil.nodes import fastsil
from hil.nodes import AppNode, EcuNode, PlantNode, run_in_process
from hil.nodes.base import grade_named, true_grade_index
from hil.report import verdict
from hil.sim.metrics import rms
from hil.sim.road import Route
from hil.transport import secoc
from hil.transport.codec import Codec

RUN_MODE_NAMES = {i: name for name, i in MODES.items()}     # 1: "regen", as hil sim says it

SETTLE_S = 3.0
REACTION_S = 1.0


@dataclass
class SilTrace:
    dt_s: float
    segment: np.ndarray
    true_grade: np.ndarray
    arrays: dict = field(default_factory=dict)


SPEED_NOISE_SIGMAS = 5.0     # a route's speed stays this many sensor sigmas below the DBC's


def check_route(cfg: VehicleConfig, route: Route) -> None:
    """The route's speeds must leave the speed sensor's noise (``SPEED_NOISE_SIGMAS`` sigma,
    plus one ADC step) below VEHICLE_SPEED's declared maximum: else the measured speed
    crosses it and every such frame is a RANGE fault (control effectively off)."""
    from hil.sim.road import MAX_SPEED_MPS

    ch = cfg.sensors.speed
    limit = MAX_SPEED_MPS - SPEED_NOISE_SIGMAS * ch.noise_std - ch.lsb
    fastest = max(seg.speed_mps for seg in route.segments)
    if fastest > limit:
        raise ConfigError(
            f"{route.name}: a segment drives {fastest:g} m/s; with the speed sensor's noise "
            f"({ch.noise_std:g} m/s) the measured speed would pass VEHICLE_SPEED's maximum "
            f"{MAX_SPEED_MPS:g} m/s: at most {limit:.4g} m/s on this vehicle")


def ecu_params(cfg: VehicleConfig, mode: str, *, controller: Optional[str] = None,
               opts: Optional[DesignOptions] = None, gains_file=None,
               params: Optional[fp.EcuParams] = None) -> fp.EcuParams:
    """The ECU calibration of a run; the ECU tick is the plant step."""
    if mode not in MODES and mode != "auto":
        raise ValueError(f"unknown mode {mode!r}")
    dt = cfg.sim.plant_dt_s
    opts = dataclasses.replace(opts, dt_s=dt) if opts else DesignOptions(dt_s=dt)
    p = params or build(cfg, opts, gains_file)
    if abs(p.dt_s - dt) > 1e-12:
        raise ValueError(f"ECU tick {p.dt_s} s differs from the plant step {dt} s")
    if controller is not None:
        if controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {controller!r}")
        target = fp.MODE_COMFORT if mode in ("auto", "passive") else MODES[mode]
        p = with_controllers(p, target, CONTROLLERS[controller])
    return p


def app_node(codec: Codec, mode: str, dt: float, policy: Optional[str] = None,
             script: Optional[list] = None, reaction_s: float = REACTION_S,
             key: Optional[bytes] = None) -> AppNode:
    """The driver of a run: ``auto`` mode accepts recommendations; a fixed mode chooses it and
    refuses the rest; ``policy`` overrides (refuse, script, interactive)."""
    if policy is None:
        policy = "auto" if mode == "auto" else "fixed"
    fixed = MODES.get(mode, fp.MODE_PASSIVE)
    return AppNode(codec, policy, mode=fixed, reaction_ticks=int(round(reaction_s / dt)),
                   script=script, dt=dt, key=key)


def run(cfg: VehicleConfig, route: Route, mode: str, seed: int, *,
        controller: Optional[str] = None, opts: Optional[DesignOptions] = None,
        gains_file=None, policy: Optional[str] = None, script: Optional[list] = None,
        params: Optional[fp.EcuParams] = None, noise_step: Optional[tuple[float, float]] = None,
        progress: Optional[Callable[[int, int], None]] = None,
        on_frame: Optional[Callable[[int, bytes], None]] = None,
        duration_s: Optional[float] = None, fixed_point: bool = False,
        fx_record: Optional[list] = None, key: Optional[bytes] = None,
        hashed: Optional[bytearray] = None, compiled: bool = True,
        leave_out: Optional[str] = None, sensor_fault: Optional[tuple] = None,
        ecu_out: Optional[list] = None) -> tuple[dict, SilTrace]:
    """Run the SIL. Returns (report dict, per-tick trace). ``on_frame(id, data)`` sees every
    frame in bus order; ``duration_s`` stops early; ``fixed_point`` runs the ECU's integer
    control path; ``fx_record`` (a list) receives its per-tick (inputs, outputs); ``key``: the
    SecOC key (default: a new one for this run); ``hashed`` (a bytearray) receives every
    tick's row of the trace hash (``hil.nodes.HASHED``), the per-tick golden traces;
    ``compiled``: the compiled lockstep loop (``hil.nodes.fastsil``) where it covers the run, else
    (and with False) the nodes of ``hil.nodes`` frame by frame: the same bytes; ``leave_out``:
    the ECU starts with this sensor out (``firmware.ecu.Ecu.leave_out``); ``sensor_fault``:
    (channel, kind, onset tick, size), a persistent fault of the plant's sensor
    (``hil.sim.sensors.SensorSuite.set_fault``); ``ecu_out`` (a list) receives the ECU's
    state as the run ends (its DTC memory: ``.diag.dtc``)."""
    check_route(cfg, route)
    p = ecu_params(cfg, mode, controller=controller, opts=opts, gains_file=gains_file,
                   params=params)
    codec = Codec()
    key = key or secoc.new_key()
    plant = PlantNode(cfg, route, seed, codec, noise_step=noise_step, key=key)
    if duration_s is not None:
        plant.n = min(plant.n, int(round(duration_s / plant.dt)))
    if sensor_fault is not None:
        plant.sensors.set_fault(*sensor_fault)
    ecu_node = EcuNode(p, codec, lockstep=True, fixed_point=fixed_point,
                       record=fx_record is not None, key=key)
    ecu_node.hashed = hashed
    if leave_out is not None:
        ecu_node.state.leave_out(leave_out)
    app = app_node(codec, mode, p.dt_s, policy, script, key=key)
    if compiled and fastsil.eligible(plant, ecu_node, app) is None:
        bus = fastsil.run(plant, ecu_node, app, on_frame=on_frame, progress=progress)
    else:
        bus = run_in_process(plant, ecu_node, app, on_frame=on_frame, progress=progress)
    if fx_record is not None:
        fx_record.extend(ecu_node.state.log)
    if ecu_out is not None:
        ecu_out.append(ecu_node.state)
    trace = merge_traces(plant.dt, plant.trace(), ecu_node.trace())
    report = build_report(cfg, route, mode, controller, seed, trace, plant.summary(),
                          ecu_node.summary(), app.summary())
    verdict.attach(report, verdict.run_checks(
        report, expected_ticks=plant.n, dt_s=plant.dt, ticks={"PLANT": plant.k,
                                                               "ECU": ecu_node.k},
        bus_frames=bus, fault_ticks=fault_ticks(trace)))
    return report, trace


def fault_ticks(trace: SilTrace) -> int:
    """ECU ticks with a bit of the fault word set."""
    return int(np.count_nonzero(trace.arrays["faults"]))


def mode_switches(mode: np.ndarray, faults: np.ndarray, reason: np.ndarray) -> int:
    """The mode logic's switches: changes of the active mode outside fail-safe ticks (a
    fail-safe opens the bridge whatever the mode; the fail-safe checks judge those ticks) and
    outside the road-holding override (safety first, whatever the mode: at least
    ``safety_hold_s`` each time, counted by ``road_holding_entries``). What is left is the
    mode the driver accepted or chose, whose switches hysteresis and dwell must keep few."""
    kept = mode[((faults.astype(np.int64) & safety.SAFETY_RELEVANT) == 0)
                & (reason != REASON_ROAD_HOLDING)]
    return int(np.count_nonzero(kept[1:] != kept[:-1]))


def road_holding_entries(reason: np.ndarray) -> int:
    """How often the road-holding override took over (ticks where it starts)."""
    on = reason == REASON_ROAD_HOLDING
    return int(np.count_nonzero(on[1:] & ~on[:-1]) + bool(len(on) and on[0]))


def _mode_shares(mode: np.ndarray) -> dict[str, float]:
    """The share of ticks in each active mode, by its run-mode name, the largest first."""
    values, counts = np.unique(mode, return_counts=True)
    order = np.argsort(-counts, kind="stable")
    return {RUN_MODE_NAMES[int(values[i])]: float(counts[i] / len(mode)) for i in order}


def merge_traces(dt: float, plant: dict, ecu_cols: dict) -> SilTrace:
    """One trace from the plant's and the ECU's per-tick records (the shorter one rules)."""
    n = min(len(plant["ba"]), len(ecu_cols["mode"]))
    arrays = {k: v[:n] for k, v in plant.items()}
    arrays.update({k: v[:n] for k, v in ecu_cols.items()})
    return SilTrace(dt, arrays.pop("segment"), arrays.pop("true_grade"), arrays)


def build_report(cfg, route, mode, controller, seed, trace: SilTrace, plant: dict, ecu: dict,
                 app: dict) -> dict:
    report = _report(cfg, route, mode, controller, seed, trace, plant["energy"],
                     ecu["trace_sha256"], ecu["akf_r_guard_hits"])
    report["driver"] = {"policy": app["policy"], "requests": app["requests"]}
    report["frames_sent"] = {"PLANT": plant["frames_sent"], "ECU": ecu["frames_sent"],
                             "APP": app["frames_sent"]}
    report["frame_faults"] = ecu["frame_faults"]
    report["ecu_arithmetic"] = ecu.get("arithmetic", "float")
    report["fx_gain_saturations"] = ecu.get("fx_gain_saturations", 0)
    report["dtcs_confirmed"] = ecu.get("dtcs_confirmed", [])
    report["plant_fallback_ticks"] = plant["fallback_ticks"]
    report["plant_missed_cmds"] = plant["missed_cmds"]
    report["plant_bad_cmd_frames"] = plant["bad_cmd_frames"]
    report["plant_stale_cmd_frames"] = plant["stale_cmd_frames"]
    report["plant_auth_failures"] = plant["auth_failures"]
    return report


def _unscored(seg, driven_s: float) -> dict:
    """A segment the run drove no longer than the settling window: listed, flagged, with no
    metrics (an RMS of what is left would be one of a handful of ticks)."""
    nan = float("nan")
    blank = {"ba_rms_mps2": nan, "sws_rms_m": nan, "dtd_rms_m": nan, "force_rms_n": nan}
    return {"grade": seg.grade, "speed_mps": seg.speed_mps, "duration_s": seg.duration_s(),
            "scored": False,
            "note": f"driven {driven_s:g} s, not longer than the {SETTLE_S:g} s settling "
                    f"window: not scored",
            "active": dict(blank), "passive": dict(blank),
            "ratio": {"ba": nan, "sws": nan, "dtd": nan}, "grade_accuracy": nan,
            "harvested_j": nan, "consumed_j": nan, "harvested_w": nan, "road_power_w": nan,
            "road_estimate_rmse_m": nan, "modes": {}, "road_holding_share": nan}


def _report(cfg, route, mode, controller, seed, trace, energy, digest, guard_hits) -> dict:
    dt = trace.dt_s
    a = trace.arrays
    settle = int(round(SETTLE_S / dt))
    segments = []
    acc_hits = acc_n = 0
    c_s = cfg.vehicle.damping_n_s_per_m
    for i, seg in enumerate(route.segments):
        idx = np.flatnonzero(trace.segment == i)
        if not len(idx):
            continue
        if len(idx) <= settle:          # nothing left after the settling window: flagged
            segments.append(_unscored(seg, len(idx) * dt))
            continue
        sel = idx[settle:]
        act = {"ba_rms_mps2": rms(a["ba"][sel]), "sws_rms_m": rms(a["sws"][sel]),
               "dtd_rms_m": rms(a["dtd"][sel]), "force_rms_n": rms(a["force"][sel])}
        pas = {"ba_rms_mps2": rms(a["p_ba"][sel]), "sws_rms_m": rms(a["p_sws"][sel]),
               "dtd_rms_m": rms(a["p_dtd"][sel]), "force_rms_n": 0.0}
        named = grade_named(seg.grade)
        hits = int(np.count_nonzero(a["grade_est"][sel] == trace.true_grade[sel]))
        if named:                       # (E-H: beyond the estimate's cap, not scored)
            acc_hits += hits
            acc_n += len(sel)
        t = len(sel) * dt
        first, last_i = sel[0], sel[-1]
        harvested = float(a["stored"][last_i] - a["stored"][first - 1 if first else 0])
        consumed = float(a["drawn"][last_i] - a["drawn"][first - 1 if first else 0])
        road_power = c_s * float(np.mean(a["p_vrel"][sel] ** 2))
        segments.append({
            "grade": seg.grade, "speed_mps": seg.speed_mps, "duration_s": seg.duration_s(),
            "scored": True, "active": act, "passive": pas,
            "ratio": {k: act[f"{k}_rms_{u}"] / pas[f"{k}_rms_{u}"]
                      for k, u in (("ba", "mps2"), ("sws", "m"), ("dtd", "m"))},
            "grade_accuracy": hits / len(sel) if named else float("nan"),
            "harvested_j": harvested, "consumed_j": consumed,
            "harvested_w": harvested / t, "road_power_w": road_power,
            "road_estimate_rmse_m": rms(a["road_est"][sel] - a["zf"][sel]),
            "modes": _mode_shares(a["mode"][sel]),
            "road_holding_share": float(np.mean(a["reason"][sel] == REASON_ROAD_HOLDING)),
        })
    switches = mode_switches(a["mode"], a["faults"], a["reason"])
    grades_seq = [s.grade for s in route.segments]
    grade_changes = sum(1 for x, y in zip(grades_seq, grades_seq[1:])
                        if true_grade_index(x) != true_grade_index(y))
    return {
        "route": route.name, "mode": mode, "controller": controller, "seed": seed,
        "vehicle": cfg.source, "duration_s": len(trace.segment) * dt,
        "segments": segments,
        "grade_accuracy": acc_hits / acc_n if acc_n else float("nan"),
        "mode_switches": switches, "grade_changes": grade_changes,
        "road_holding_entries": road_holding_entries(a["reason"]), "settle_s": SETTLE_S,
        "trace_sha256": digest,
        "energy": energy,
        "akf_r_guard_hits": guard_hits,
    }
