"""A vehicle space's campaign car by car (``[space]``): the pass rate of its cars with a
95 % confidence interval, the worst cars with the command that reproduces each, a
sensitivity analysis of each outcome over the sampled parameters, and figures.

The sensitivity is RBD-FAST (SALib's ``rbd_fast``: first-order indices S1, the share of an
outcome's variance one parameter explains alone, with a bootstrap 95 % interval), valid for
any sample and so for the Latin hypercube or Sobol design the space drew. It is computed per
base car (the default car and the SUV are different populations). The outcomes per car,
each a mean over its seeds: the value each segment is judged by in the mode its grade gets in
auto (BA ratio in comfort, DTD in safety, the sum of the three in comprehensive), its gap to
the car's own limit under the per-drive bound, and the share of the scored drive spent
passive (on the acceptance route, where auto drives no grade passive, the fail-safe's
share)."""

from __future__ import annotations

import json
import math
import sqlite3
from pathlib import Path
from typing import Optional

from hil.validate.acceptance import GRADE_MODE
from hil.validate.campaign.case import JUDGED, judged_ratio, judged_value
from hil.validate.campaign.spec import label

RBD_M = 10                  # RBD-FAST's harmonics (SALib's default); it needs N > 2 M cars
SENSITIVITY_METHOD = "RBD-FAST (SALib 1.6.0, first-order S1 with a bootstrap 95 % interval)"


def summary(db_path: Path) -> Optional[dict]:
    """The space's summary from a campaign database; None when its cars were not sampled."""
    cars = _cars(db_path)
    if not cars:
        return None
    out = {"method": SENSITIVITY_METHOD, "bases": {}}
    for base in sorted({c["base"] for c in cars.values()}):
        group = [c for c in cars.values() if c["base"] == base]
        params = sorted({k for c in group for k in c["factors"]})
        outputs = sorted({k for c in group for k in c["outcomes"]})
        passed = sum(c["pass"] for c in group)
        lo, hi = proportion_ci(passed, len(group))
        ranked = sorted(group, key=_badness)
        out["bases"][base] = {
            "cars": len(group), "passed": passed, "pass_rate": passed / len(group),
            "pass_rate_ci95": [lo, hi], "parameters": params, "outputs": outputs,
            "sensitivity": sensitivity(group, params, outputs),
            # the ten worst cars, then every failing car, each with its command
            "worst": [_car(c) for c in ranked[:10]],
            "failing": [_car(c) for c in ranked if not c["pass"]],
            "table": [{"sample": c["sample"], "pass": c["pass"], "factors": c["factors"],
                       "outcomes": c["outcomes"]}
                      for c in sorted(group, key=lambda c: c["sample"])]}
    return out


def _car(c: dict) -> dict:
    return {"car": c["label"], "sample": c["sample"], "pass": c["pass"],
            "factors": c["factors"], "outcomes": c["outcomes"], "failed": c["failed"],
            "command": c["command"]}


def proportion_ci(k: int, n: int) -> tuple[float, float]:
    """The exact (Clopper-Pearson) 95 % interval of a pass rate k / n."""
    if n == 0:
        return (float("nan"), float("nan"))
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(0.95, method="exact")
    return (float(ci.low), float(ci.high))


def _cars(db_path: Path) -> dict:
    """Per sampled car: its base, factors, pass (every seed), failures, command, outcomes."""
    db = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)
    try:
        cases = db.execute("SELECT case_id, verdict, failed, command, case_json FROM cases "
                           "ORDER BY case_id").fetchall()
        segs = db.execute("SELECT case_id, idx, grade, speed_mps, ba_ratio, sws_ratio, "
                          "dtd_ratio, gap, metrics FROM segments WHERE scored = 1 "
                          "ORDER BY case_id, idx").fetchall()
    finally:
        db.close()
    by_case: dict[str, list] = {}
    for s in segs:
        by_case.setdefault(s[0], []).append(s)
    cars: dict[tuple, dict] = {}
    for case_id, verdict, failed, command, case_json in cases:
        case = json.loads(case_json)
        v = case["vehicle"]
        if "sample" not in v:
            continue
        car = cars.setdefault((v["name"], v["sample"]), {
            "base": v["name"], "sample": v["sample"], "label": label(v),
            "factors": dict(v["factors"]), "pass": True,
            "failed": [], "command": command, "runs": [], "score": -1.0})
        ok = verdict == "pass"
        car["pass"] = car["pass"] and ok
        for f in json.loads(failed):
            f = _clause(f)
            if f not in car["failed"]:
                car["failed"].append(f)
        run = _outcomes(case["mode"], by_case.get(case_id, []))
        car["runs"].append(run)
        score = (0.0 if ok else 1.0) + run.get("passive_share", 0.0)
        if score > car["score"]:          # the command of its worst case
            car["score"], car["command"] = score, command
    for car in cars.values():
        keys = sorted({k for r in car["runs"] for k in r})
        car["outcomes"] = {k: _mean([r[k] for r in car["runs"] if k in r]) for k in keys}
    return cars


def _clause(failure: str) -> str:
    """A failure without its values, so a car's seeds list each clause once:
    'segment 3 (D@20): ba 1.051 > 1.000' -> 'segment 3 (D@20): ba'."""
    if failure.startswith("segment") and ": " in failure:
        where, what = failure.split(": ", 1)
        return f"{where}: {'; '.join(dict.fromkeys(w.split()[0] for w in what.split('; ')))}"
    return failure


def _outcomes(mode: str, segs: list) -> dict:
    """One drive's outcomes: per segment its judged value and gap, and the passive share."""
    out, passive = {}, []
    for _, idx, grade, speed, ba, sws, dtd, gap, metrics in segs:
        m = json.loads(metrics)
        judged = GRADE_MODE.get(grade, "regen") if mode == "auto" else mode
        if judged not in JUDGED:          # (energy feedback, passive: judged by BA)
            judged = "comfort"
        name = f"{idx + 1}:{grade}@{speed:g}"
        ratio = {"ba": ba, "sws": sws, "dtd": dtd}
        if all(x is not None for x in ratio.values()):
            out[f"{name} {judged_ratio(judged)}"] = judged_value(judged, ratio)
        if gap is not None:
            out[f"{name} gap"] = gap
        passive.append((m.get("modes") or {}).get("passive", 0.0))
    if passive:
        out["passive_share"] = sum(passive) / len(passive)
    return out


def _mean(v: list) -> float:
    return sum(v) / len(v) if v else float("nan")


def _badness(car: dict) -> tuple:
    """Failing cars first, the most time passive (fail-safe) first, then the largest gap."""
    o = car["outcomes"]
    gaps = [v for k, v in o.items() if k.endswith(" gap") and math.isfinite(v)]
    return (car["pass"], -o.get("passive_share", 0.0), -(max(gaps) if gaps else -1e9),
            car["sample"])


def sensitivity(cars: list, params: list, outputs: list) -> dict:
    """Per output, each parameter's RBD-FAST first-order index S1 and its 95 % half-width
    (SALib), or the reason there is none (too few cars, an output that does not vary)."""
    import numpy as np

    out = {}
    if len(cars) <= 2 * RBD_M:
        return {"skipped": f"{len(cars)} cars: RBD-FAST needs more than {2 * RBD_M}"}
    X = np.array([[c["factors"].get(p, 1.0) for p in params] for c in cars])
    bounds = [[float(X[:, j].min()), float(X[:, j].max())] for j in range(len(params))]
    for name in outputs:
        Y = np.array([c["outcomes"].get(name, float("nan")) for c in cars])
        keep = np.isfinite(Y)
        if keep.sum() <= 2 * RBD_M or float(np.ptp(Y[keep])) == 0.0:
            out[name] = {"skipped": "does not vary" if keep.sum() > 2 * RBD_M else
                         f"{int(keep.sum())} cars with a value"}
            continue
        from SALib.analyze import rbd_fast

        problem = {"num_vars": len(params), "names": params, "bounds": bounds}
        res = rbd_fast.analyze(problem, X[keep], Y[keep], M=RBD_M, num_resamples=200,
                               seed=1)
        out[name] = {p: {"S1": float(res["S1"][j]), "ci95": float(res["S1_conf"][j])}
                     for j, p in enumerate(params)}
    return out


def influential(base: dict, n: int = 2) -> list[str]:
    """The ``n`` parameters with the largest S1 summed over the outputs."""
    total = {p: 0.0 for p in base["parameters"]}
    for res in base["sensitivity"].values():
        if isinstance(res, dict) and "skipped" not in res:
            for p, s in res.items():
                total[p] += max(0.0, s["S1"])
    return sorted(total, key=lambda p: -total[p])[:n]


def cars_markdown(rep: dict) -> str:
    """Every failing sampled car (each with what failed and the command of its worst case)
    and every infeasible one (with its reason), as Markdown."""
    lines = [f"# `{rep['campaign']}`: the failing and infeasible cars", "",
             f"{rep['passed']}/{rep['cases']} cases pass; software "
             f"{', '.join(rep['software_versions'])}. Written by `python -m hil "
             "campaign-report DB --cars FILE`; each command names the database as the "
             "campaign wrote it.", ""]
    space = rep.get("space") or {"bases": {}}
    for base, b in space["bases"].items():
        lines += [f"## {base}: {len(b['failing'])} of {b['cars']} cars fail", ""]
        if b["failing"]:
            lines += ["| car | factors | failed | reproduce |", "|---|---|---|---|"]
        for c in b["failing"]:
            f = ", ".join(f"{k.split('_')[0]} ×{v:.3f}" for k, v in sorted(c["factors"].items()))
            lines.append(f"| {c['sample']} | {f} | {'; '.join(c['failed'])} | "
                         f"`{c['command']}` |")
        lines.append("")
    lines += [f"## Infeasible: {len(rep['infeasible'])} cars", ""]
    lines += [f"- {x['vehicle']}: {x['reason']}" for x in rep["infeasible"]]
    return "\n".join(lines).rstrip() + "\n"


def figures(space: dict, out: Path) -> list[Path]:
    """Per base car: each outcome against each parameter (a dot per car, failing cars red),
    and the pass/fail map over the two most influential parameters."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for base, b in space["bases"].items():
        params, outputs = b["parameters"], b["outputs"]
        rows = b["table"]
        ok = [r["pass"] for r in rows]
        fig, axes = plt.subplots(len(outputs), len(params), squeeze=False,
                                 figsize=(1.9 * len(params) + 1, 1.5 * len(outputs) + 1),
                                 sharex="col", sharey="row")
        for i, name in enumerate(outputs):
            for j, p in enumerate(params):
                ax = axes[i][j]
                for good, colour, mark in ((True, "C0", "o"), (False, "C3", "x")):
                    pts = [(r["factors"].get(p, 1.0), r["outcomes"].get(name, float("nan")))
                           for r, g in zip(rows, ok) if g == good]
                    if pts:
                        ax.scatter(*zip(*pts), s=8, c=colour, marker=mark, linewidths=0.8)
                ax.grid(alpha=0.3)
                ax.tick_params(labelsize=6)
                if i == len(outputs) - 1:
                    ax.set_xlabel(f"{p} (factor)", fontsize=7)
                if j == 0:
                    ax.set_ylabel(name, fontsize=7)
        fig.suptitle(f"{space.get('campaign', '')}: {base}, each outcome against each "
                     f"parameter (blue: the car passes, red x: it fails); "
                     f"{b['passed']}/{b['cars']} cars pass", fontsize=9)
        fig.tight_layout()
        path = out / f"space_{base}.png"
        fig.savefig(path, dpi=80, metadata={"Software": None})
        plt.close(fig)
        paths.append(path)
        top = influential(b)
        if len(top) == 2:
            fig, ax = plt.subplots(figsize=(5.5, 4.5))
            for good, colour, mark, what in ((True, "C0", "o", "pass"),
                                             (False, "C3", "x", "fail")):
                pts = [(r["factors"].get(top[0], 1.0), r["factors"].get(top[1], 1.0))
                       for r, g in zip(rows, ok) if g == good]
                if pts:
                    ax.scatter(*zip(*pts), s=18, c=colour, marker=mark,
                               label=f"{len(pts)} cars {what}")
            ax.set_xlabel(f"{top[0]} (factor)")
            ax.set_ylabel(f"{top[1]} (factor)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
            ax.set_title(f"{base}: pass/fail over its two most influential parameters",
                         fontsize=9)
            fig.tight_layout()
            path = out / f"passfail_{base}.png"
            fig.savefig(path, dpi=90, metadata={"Software": None})
            plt.close(fig)
            paths.append(path)
    return paths


def render(space: dict, con) -> None:
    """The space's part of ``campaign-report``'s text."""
    from rich.table import Table

    for base, b in space["bases"].items():
        lo, hi = b["pass_rate_ci95"]
        con.print(f"{base}: {b['passed']}/{b['cars']} sampled cars pass every seed "
                  f"({100 * b['pass_rate']:.1f} %, 95 % CI {100 * lo:.1f}–{100 * hi:.1f} %)")
        sens = b["sensitivity"]
        if "skipped" in sens:
            con.print(f"  sensitivity: {sens['skipped']}")
        else:
            t = Table(title=f"{base}: sensitivity, {space['method']}")
            t.add_column("outcome")
            for p in b["parameters"]:
                t.add_column(p.replace("_n_per_m", "").replace("_n_s_per_m", "")
                             .replace("_kg", "").replace("_nm_per_a", "").replace("_ohm", ""),
                             justify="right")
            for name, res in sens.items():
                if "skipped" in res:
                    t.add_row(name, *(["-"] * len(b["parameters"])))
                else:
                    t.add_row(name, *(f"{res[p]['S1']:.2f}" for p in b["parameters"]))
            con.print(t)
        shown = b["worst"] + b["failing"][len(b["worst"]):]
        con.print(f"{base}: the worst cars (failing first, the longest passive first) and "
                  "every failing car, each with the command that reproduces its worst case:")
        for w in shown:
            con.print(f"  {w['car']}: {'passes' if w['pass'] else 'FAILS'}, passive "
                      f"{100 * w['outcomes'].get('passive_share', 0.0):.0f} % of the drive; "
                      f"{'; '.join(w['failed']) or '-'}\n    {w['command']}", soft_wrap=True)
