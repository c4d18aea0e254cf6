"""The SIL acceptance in one place: the bounds a drive in each mode meets (its ratios to the
passive car on the same road; ``tests/test_sil_acceptance.py`` asserts them on three seeds,
``hil.validate.campaign`` judges every campaign case by them), and the mode the ECU drives on each
grade in auto (``firmware.modes.GRADE_TO_MODE``, by the names ``hil sim`` uses)."""

from __future__ import annotations

from typing import Optional

from firmware.modes import GRADE_TO_MODE
from hil.config import RUN_MODES

# the ratio bounds by mode: ``max`` bounds every ratio, ``sum_eq43`` the sum of the three
# ratios over the vehicle's own Eq. (43) limit
ACCEPTANCE = {"comfort": {"ba": 0.85, "sws": 1.0, "dtd": 1.02},
              "safety": {"dtd": 0.90, "ba": 1.0},
              "comprehensive": {"max": 1.0, "sum_eq43": 1.05}}
# "relative" acceptance (a campaign's option): these bounds move with the vehicle's own limit
# (the default car's limits are 0.788 and 0.844: a vehicle whose own limit is above 0.85 or
# 0.90 could not pass the absolute bound with any controller); the others bound ratios to
# passive, or are relative already (sum_eq43)
RELATIVE_KEY = {"comfort": "ba", "safety": "dtd"}
# energy feedback: the share of the road's power into the corner harvested, ratios to passive
REGEN_HARVEST_SHARE = 0.25
REGEN_ACCEPTANCE = {"ba": 1.1, "dtd": 1.1}
GRADE_ACCURACY = 0.95       # the share of a drive whose grade the ECU estimates right
OWN_LIMIT_GAP = 0.03        # a design's mean ratio above its vehicle's own limit, at most

_NAME = {i: name for name, i in RUN_MODES.items()}          # 1: "regen"
GRADE_MODE = {grade: _NAME[m] for grade, m in zip("ABCD", GRADE_TO_MODE)}


def violations(mode: str, ratio: dict, eq43_limit: Optional[float] = None,
               raised: Optional[dict] = None) -> list[str]:
    """The bounds of ``mode``'s acceptance that ``ratio`` (a segment's ratios) exceeds, each
    as ``"key got > bound"``. ``eq43_limit``: the vehicle's Eq. (43) limit (``sum_eq43``'s
    reference, comprehensive mode's only); ``raised``: what to add to some bounds (a
    campaign's relative acceptance)."""
    out = []
    for key, bound in ACCEPTANCE[mode].items():
        if raised and key in raised:
            bound += raised[key]
        if key == "max":
            got = max(ratio.values())
        elif key == "sum_eq43":
            got = sum(ratio.values()) / eq43_limit
        else:
            got = ratio[key]
        if got > bound:
            out.append(f"{key} {got:.3f} > {bound:.3f}")
    return out
