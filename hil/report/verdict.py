"""Every run ends with a verdict: a list of checks (name, value, limit, ok), ``pass`` only when
all hold, exit code 1 otherwise, and, with ``--junit FILE``, the same checks as JUnit XML (one
test case per check) for a CI to read.

The checks of a drive (``hil sim``, ``hil run``; :func:`run_checks`):

* ``ticks.PLANT``, ``ticks.ECU``: each node ran the route's ticks (or ``--duration``'s);
* ``span_s``: the report covers exactly that span;
* ``bus.<MESSAGE>``: the frames of each message on the bus (the log of ``hil run``, the FIFO of
  ``hil sim``) are the frames the nodes sent, message by message;
* ``app.answers``: the app answered every MODE_RECOMMEND (lockstep);
* without injected faults, in lockstep: no frame fault, no tick with a fault bit (fail-safe),
  no tick of the plant's passive fallback, no tick stepped without a command, no invalid,
  stale or unauthentic (SecOC) command at the plant (in realtime: no invalid or unauthentic
  one); in realtime
  the same under limits (:class:`Limits`, options ``--max-missed-ratio``/``--max-lost-ratio``);
* ``mode_switches`` in auto mode: at most the route's grade changes + 1 (the active mode's
  changes outside fail-safe ticks: a fail-safe opens the bridge whatever the mode, and the
  fail-safe checks above judge it).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Optional

PASS, FAIL = "pass", "fail"
EXIT_FAIL = 1


@dataclass(frozen=True)
class Limits:
    """Realtime pacing's limits (lockstep allows nothing). Missed deadlines: ticks the plant
    stepped without the command answering its sensor frame, and ticks of the plant's passive
    fallback, each over the ticks run. Lost: sensor frames the ECU never processed, and ticks
    with a fault bit, each over the ticks run. The defaults hold on an idle 2-core host
    (``make bench`` here: 0.14 to 0.41 % missed over 60 s); a host under load fails them, as
    it should: its timing is not the bench's."""
    max_missed_ratio: float = 0.01
    max_lost_ratio: float = 0.001


@dataclass(frozen=True)
class Check:
    name: str
    value: Any
    limit: str
    ok: bool

    def as_dict(self) -> dict:
        return asdict(self)


def check(name: str, value, op: str, limit) -> Check:
    """``value op limit`` (op one of ==, <=, >=); a NaN value fails."""
    if isinstance(value, float) and not math.isfinite(value):
        ok = False
    elif op == "==":
        ok = value == limit
    elif op == "<=":
        ok = value <= limit
    elif op == ">=":
        ok = value >= limit
    else:
        raise ValueError(f"unknown comparison {op!r}")
    return Check(name, value, f"{op} {limit:g}" if isinstance(limit, float) else f"{op} {limit}",
                 bool(ok))


def verdict(checks: list[Check]) -> str:
    return PASS if checks and all(c.ok for c in checks) else FAIL


def attach(report: dict, checks: list[Check]) -> dict:
    """Put ``checks`` and ``verdict`` into ``report`` (last keys); returns it."""
    report["checks"] = [c.as_dict() for c in checks]
    report["verdict"] = verdict(checks)
    return report


def exit_code(report: dict) -> int:
    return 0 if report.get("verdict") == PASS else EXIT_FAIL


def run_checks(report: dict, *, expected_ticks: int, dt_s: float, ticks: dict[str, int],
               bus_frames: dict[str, int], pace: str = "lockstep", injected: bool = False,
               lost_sensor_frames: int = 0, missed_deadlines: int = 0, fault_ticks: int = 0,
               limits: Optional[Limits] = None,
               outside_frames: Optional[dict[str, int]] = None) -> list[Check]:
    """The checks of one drive from its report (``hil.nodes.sil.build_report``). ``ticks``: per node
    (PLANT, ECU) the ticks it ran; ``bus_frames``: per message name the frames seen on the bus;
    ``fault_ticks``: ECU ticks with a fault bit set; ``outside_frames``: per message name the
    frames a known outside sender put on the bus (the fault campaign's attacker on vcan0,
    where no hub drops them)."""
    limits = limits or Limits()
    out = [check(f"ticks.{node}", int(n), "==", expected_ticks) for node, n in ticks.items()]
    out.append(check("span_s", report["duration_s"], "==", expected_ticks * dt_s))
    sent: dict[str, int] = {}
    for per_node in report["frames_sent"].values():
        for name, n in per_node.items():
            sent[name] = sent.get(name, 0) + n
    for name, n in (outside_frames or {}).items():
        sent[name] = sent.get(name, 0) + n
    for name in sorted(set(sent) | set(bus_frames)):
        out.append(check(f"bus.{name}", bus_frames.get(name, 0), "==", sent.get(name, 0)))
    if pace == "lockstep":
        out.append(check("app.answers", sent.get("DRIVER_REQUEST", 0), "==",
                         sent.get("MODE_RECOMMEND", 0)))
    if not injected:
        frame_faults = sum(report["frame_faults"].values())
        if pace == "lockstep":
            out += [check("frame_faults", frame_faults, "==", 0),
                    check("failsafe_ticks", fault_ticks, "==", 0),
                    # a fault-free drive confirms no DTC (a false alarm names a good part)
                    check("dtcs_confirmed", len(report.get("dtcs_confirmed", [])), "==", 0),
                    check("plant_fallback_ticks", report["plant_fallback_ticks"], "==", 0),
                    check("plant_missed_cmds", report["plant_missed_cmds"], "==", 0),
                    check("plant_bad_cmd_frames", report["plant_bad_cmd_frames"], "==", 0),
                    check("plant_stale_cmd_frames", report["plant_stale_cmd_frames"], "==",
                          0),
                    check("plant_auth_failures", report["plant_auth_failures"], "==", 0)]
        else:
            n = max(1, expected_ticks)
            out.append(check("plant_bad_cmd_frames", report["plant_bad_cmd_frames"], "==", 0))
            out.append(check("plant_auth_failures", report["plant_auth_failures"], "==", 0))
            out += [check("missed_deadline_ratio", missed_deadlines / n, "<=",
                          limits.max_missed_ratio),
                    check("lost_frame_ratio", lost_sensor_frames / n, "<=",
                          limits.max_lost_ratio),
                    check("failsafe_ratio", fault_ticks / n, "<=", limits.max_lost_ratio),
                    # (the plant falls back when commands miss their deadlines: the first
                    # tick's, before the ECU's first answer, always does)
                    check("plant_fallback_ratio", report["plant_fallback_ticks"] / n, "<=",
                          limits.max_missed_ratio)]
    if report["mode"] == "auto":
        out.append(check("mode_switches", report["mode_switches"], "<=",
                         report["grade_changes"] + 1))
    return out


def add_arguments(parser, realtime: bool = False) -> None:
    parser.add_argument("--junit", metavar="FILE",
                        help="also write the verdict's checks as JUnit XML (one test case each)")
    if realtime:
        d = Limits()
        parser.add_argument("--max-missed-ratio", type=_ratio, default=d.max_missed_ratio,
                            metavar="R", help="realtime: the largest share of missed deadlines "
                            f"(and of plant fallback ticks) that passes (default {d.max_missed_ratio:g})")
        parser.add_argument("--max-lost-ratio", type=_ratio, default=d.max_lost_ratio,
                            metavar="R", help="realtime: the largest share of ticks with a lost "
                            "sensor frame, or with a fault bit, that passes "
                            f"(default {d.max_lost_ratio:g})")


def limits_of(args) -> Limits:
    d = Limits()
    return Limits(getattr(args, "max_missed_ratio", d.max_missed_ratio),
                  getattr(args, "max_lost_ratio", d.max_lost_ratio))


def _ratio(text: str) -> float:
    import argparse

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a ratio in [0, 1], got {text!r}")
    return value


def write_junit(path: str | Path, suite: str, checks: list[Check],
                time_s: Optional[float]) -> Path:
    """The checks as a JUnit XML file: one ``testsuite`` named ``suite`` whose ``time`` is
    the run's wall time ``time_s`` (None: not measured, e.g. a run that did not finish: no
    ``time``), one ``testcase`` per check (classname the suite, name the check) with its
    value and limit as properties and a ``failure`` when it does not hold. A check is judged
    once the run is over and takes no time of its own: its testcase carries no ``time``
    (an attribute JUnit readers take as optional) rather than a made-up one. Written
    atomically."""
    root = ET.Element("testsuites")
    failures = sum(not c.ok for c in checks)
    ts = ET.SubElement(root, "testsuite", name=suite, tests=str(len(checks)),
                       failures=str(failures), errors="0", skipped="0")
    if time_s is not None:
        ts.set("time", f"{time_s:.3f}")
    for c in checks:
        tc = ET.SubElement(ts, "testcase", classname=suite, name=c.name)
        props = ET.SubElement(tc, "properties")
        ET.SubElement(props, "property", name="value", value=_text(c.value))
        ET.SubElement(props, "property", name="limit", value=c.limit)
        if not c.ok:
            f = ET.SubElement(tc, "failure", message=f"{c.name} = {_text(c.value)}, "
                                                     f"want {c.limit}", type="check")
            f.text = f"{c.name}: {_text(c.value)} (limit {c.limit})"
    ET.indent(root)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from hil.cli import write_atomic

    return write_atomic(path, ET.tostring(root, encoding="utf-8", xml_declaration=True))


def _text(value) -> str:
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def render(report: dict) -> None:
    """The verdict line and the failed checks (rich, on stdout)."""
    from rich.console import Console

    console = Console()
    checks = report.get("checks", [])
    bad = [c for c in checks if not c["ok"]]
    for c in bad:
        console.print(f"  [red]FAIL[/red] {c['name']} = {_text(c['value'])} (limit {c['limit']})")
    if report.get("dtcs_confirmed"):         # (by name: what a technician would read out)
        console.print(f"  confirmed DTCs: {', '.join(report['dtcs_confirmed'])}")
    word = "[green]PASS[/green]" if report.get("verdict") == PASS else "[red]FAIL[/red]"
    console.print(f"verdict: {word} ({len(checks) - len(bad)}/{len(checks)} checks hold)")
