"""What the driver app tells the driver, from the frames it receives (``AppNode.view``): the
recommended mode with the estimated grade and why, the active mode, the ride figures, the
energy and the ECU's faults, by name. One description for the terminal app and the web page
(``hil.apps.webapp``)."""

from __future__ import annotations

from firmware import modes as fm
from firmware import safety
from firmware.diag.degrade import STATE_NAMES
from firmware.params import GRADE_NAMES, MODE_NAMES
from hil.transport.codec import fault_word

# why each mode suits its grade (the mode of each grade is firmware.modes.GRADE_TO_MODE)
SUITS = {"energy": "a smooth road: harvest energy", "comfort": "ride comfort first",
         "safety": "road holding first", "comprehensive": "a rough road: comfort and road "
         "holding together"}


def name_of(names, value, unknown):
    """The name of an enumerated value (a mode, a grade), ``unknown`` where there is none."""
    return names[int(value)] if value is not None and 0 <= int(value) < len(names) else unknown


def describe(view: dict, t_s: float) -> dict:
    """The driver's picture of the ECU, JSON-ready."""
    rec = view.get("REC_RECOMMENDED_MODE")
    grade = name_of(GRADE_NAMES, view.get("REC_ESTIMATED_GRADE",
                                        view.get("ESTIMATED_GRADE")), "unknown")
    reason = int(view.get("REC_REASON", view.get("REASON", fm.REASON_NONE)) or 0)
    faults = safety.fault_names(fault_word(view))
    degraded = STATE_NAMES[int(view.get("DEGRADED", 0) or 0) % len(STATE_NAMES)]
    if degraded == "fail_safe_latched":
        why = ("fail-safe latched: a second fault while a sensor was out (passive damping "
               "until the next start; read the DTCs)")
    elif reason == fm.REASON_DEGRADED:
        why = ("a sensor is out (read the DTCs): this mode is not kept without it, passive "
               "damping; choose one it keeps")
    elif reason == fm.REASON_FAULT:
        why = "fail-safe: " + (", ".join(faults) or "a safety-relevant fault") + \
              " (passive damping until it clears)"
    elif reason == fm.REASON_ROAD_HOLDING:
        why = "safety override: the tyre-deflection RMS is over its limit (road holding first)"
    elif grade in GRADE_NAMES:
        mode = MODE_NAMES[fm.GRADE_TO_MODE[GRADE_NAMES.index(grade)]]
        why = f"estimated road grade {grade}: {mode} mode, {SUITS[mode]}"
    else:
        why = "the road grade is not estimated yet"
    return {
        "t_s": round(t_s, 3),
        "recommended": name_of(MODE_NAMES, rec, None) if rec is not None else None,
        "grade": grade,
        "why": why,
        "override": bool(view.get("REC_OVERRIDE", 0)),
        "active": name_of(MODE_NAMES, view.get("ACTIVE_MODE"), None),
        "speed_mps": view.get("SPEED"),
        "ba_rms_mps2": view.get("BA_RMS"),
        "dtd_rms_mm": None if view.get("DTD_RMS") is None else 1e3 * view["DTD_RMS"],
        "stored_j": view.get("STORED_ENERGY"),
        "drawn_j": view.get("SUPPLY_ENERGY"),
        "faults": faults,
        "degraded": degraded,
        "modes": list(MODE_NAMES),
    }


def recommendation_line(d: dict) -> str:
    """The terminal app's line when the recommendation changes."""
    return (f"app: t={d['t_s']:7.2f} s  ECU recommends {d['recommended']} ({d['why']}); "
            f"active {d['active']}")
