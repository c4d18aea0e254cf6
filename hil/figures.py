"""Report files of a SIL or HIL run: ``report.json``, ``report.md`` and PNG figures
(time series as in the paper's Figs. 13/15, grade and mode timeline, road estimate against
the truth, energy)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from firmware.params import GRADE_NAMES, MODE_NAMES

FIGURES = ("timeseries.png", "modes.png", "road.png", "energy.png")


def _clean(value):
    from hil.cli import _clean as clean

    return clean(value)


def write_outputs(out: Path, report: dict, trace) -> list[Path]:
    """Write report.json, report.md and the figures into ``out``; returns the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(_clean(report), indent=2) + "\n")
    tmp.replace(path)
    figs = write_figures(out, report, trace)
    md = out / "report.md"
    md.write_text(markdown(report, [f.name for f in figs]))
    return [path, md, *figs]


def markdown(report: dict, figures: list[str]) -> str:
    bench = report.get("bench", {"harness": "sil"})
    lines = [f"# {bench.get('harness', 'sil').upper()} run: route `{report['route']}`, "
             f"mode `{report['mode']}`, seed {report['seed']}", ""]
    if report.get("incomplete"):
        lines += [f"**INCOMPLETE**: {report['incomplete']}", ""]
    if "verdict" in report:
        checks = report["checks"]
        bad = [c for c in checks if not c["ok"]]
        lines += [f"**Verdict: {report['verdict'].upper()}** "
                  f"({len(checks) - len(bad)}/{len(checks)} checks hold)", ""]
        lines += [f"- FAIL `{c['name']}` = {c['value']} (limit {c['limit']})" for c in bad]
        lines += [""] if bad else []
    lines += [f"- vehicle: `{report['vehicle']}`",
              f"- duration: {report['duration_s']:.1f} s simulated"
              + (f", {bench['wall_s']:.1f} s wall (RTF {bench['rtf']:.2f}), pace "
                 f"{bench.get('pace')}, bus {bench.get('bus')}" if "wall_s" in bench else ""),
              f"- trace_sha256: `{report['trace_sha256']}`",
              f"- grade accuracy {report['grade_accuracy']:.3f}; {report['mode_switches']} mode "
              f"switches for {report['grade_changes']} grade changes",
              f"- driver: {report['driver']['policy']}, requests {report['driver']['requests']}",
              f"- energy: harvested {report['energy']['stored_j']:.1f} J, drawn from the bus "
              f"{report['energy']['supply_drawn_j']:.1f} J", ""]
    if "realtime" in bench:
        rt = bench["realtime"]
        lines += [f"- realtime: missed deadlines {rt['missed_deadlines']} "
                  f"({rt['missed_deadline_ratio']:.4f}), lag p50 {rt['lag_p50_us']:.0f} us, "
                  f"p99 {rt['lag_p99_us']:.0f} us, max {rt['lag_max_us']:.0f} us", ""]
    lines += ["Ratios are active / passive twin RMS on the same road, after "
              f"{report['settle_s']:g} s of each segment.", "",
              "| segment | BA | SWS | DTD | BA m/s² | SWS mm | DTD mm | grade ok | harvested W "
              "| drawn W | road est. RMSE mm |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in report["segments"]:
        r, a, t = s["ratio"], s["active"], s["duration_s"]
        if not s.get("scored", True):
            lines.append(f"| {s['grade']}@{s['speed_mps']:g} m/s | {s['note']} |"
                         + " |" * 10)
            continue
        lines.append(
            f"| {s['grade']}@{s['speed_mps']:g} m/s | {r['ba']:.3f} | {r['sws']:.3f} | "
            f"{r['dtd']:.3f} | {a['ba_rms_mps2']:.3f} | {1e3 * a['sws_rms_m']:.2f} | "
            f"{1e3 * a['dtd_rms_m']:.2f} | {s['grade_accuracy']:.2f} | {s['harvested_w']:.2f} | "
            f"{s['consumed_j'] / t:.1f} | {1e3 * s['road_estimate_rmse_m']:.1f} |")
    lines += ["", "Frames sent: " + ", ".join(
        f"{node} {sum(c.values())}" for node, c in report["frames_sent"].items()), ""]
    for f in figures:
        lines += [f"![{f}]({f})", ""]
    return "\n".join(lines)


def write_figures(out: Path, report: dict, trace) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = trace.arrays
    n = len(trace.segment)
    dt = trace.dt_s
    step = max(1, n // 20000)
    t = np.arange(n)[::step] * dt
    paths = []
    title = f"{report['route']}, mode {report['mode']}, seed {report['seed']}"

    fig, axes = plt.subplots(3, 1, figsize=(11, 7), sharex=True)
    for ax, key, label, scale in ((axes[0], "ba", "BA (m/s²)", 1.0),
                                  (axes[1], "sws", "SWS (mm)", 1e3),
                                  (axes[2], "dtd", "DTD (mm)", 1e3)):
        ax.plot(t, a[f"p_{key}"][::step] * scale, color="0.65", lw=0.5, label="passive")
        ax.plot(t, a[key][::step] * scale, color="C0", lw=0.5, label="ECU")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[0].set_title(f"Time series: {title}")
    axes[-1].set_xlabel("t (s)")
    paths.append(_save(fig, out / FIGURES[0]))

    fig, ax = plt.subplots(2, 1, figsize=(11, 5), sharex=True)
    ge = a["grade_est"].astype(float)
    ge[ge > 3] = np.nan
    ax[0].step(t, trace.true_grade[::step], where="post", color="k", label="true")
    ax[0].step(t, ge[::step], where="post", color="C1", label="estimated")
    ax[0].set_yticks(range(4), list(GRADE_NAMES))
    ax[0].set_ylabel("grade")
    ax[0].legend(loc="upper right")
    ax[0].set_title(f"Grade and mode: {title}")
    ax[1].step(t, a["recommended"][::step], where="post", color="C2", label="recommended")
    ax[1].step(t, a["mode"][::step], where="post", color="C3", label="active")
    ax[1].set_yticks(range(len(MODE_NAMES)), list(MODE_NAMES))
    ax[1].legend(loc="upper right")
    ax[1].set_xlabel("t (s)")
    for x in ax:
        x.grid(alpha=0.3)
    paths.append(_save(fig, out / FIGURES[1]))

    fig, ax = plt.subplots(2, 1, figsize=(11, 5))
    mid = n // 2
    w = slice(max(0, mid - int(2.5 / dt)), min(n, mid + int(2.5 / dt)))
    tw = np.arange(n)[w] * dt
    ax[0].plot(tw, a["zf"][w] * 1e3, color="k", lw=0.8, label="true road")
    ax[0].plot(tw, a["road_est"][w] * 1e3, color="C0", lw=0.8, label="AKF estimate")
    ax[0].set_ylabel("road (mm)")
    ax[0].legend(loc="upper right")
    ax[0].set_title(f"Road estimate against the truth (5 s window): {title}")
    ax[1].plot(tw, a["dtd"][w] * 1e3, color="k", lw=0.8, label="true DTD")
    ax[1].plot(tw, a["dtd_est"][w] * 1e3, color="C1", lw=0.8, label="estimated DTD")
    ax[1].set_ylabel("DTD (mm)")
    ax[1].set_xlabel("t (s)")
    ax[1].legend(loc="upper right")
    for x in ax:
        x.grid(alpha=0.3)
    paths.append(_save(fig, out / FIGURES[2]))

    fig, ax = plt.subplots(figsize=(11, 3.5))
    ax.plot(t, a["stored"][::step], color="C2", label="harvested into storage")
    ax.plot(t, a["drawn"][::step], color="C3", label="drawn from the bus")
    ax.set_ylabel("energy (J)")
    ax.set_xlabel("t (s)")
    ax.set_title(f"Energy: {title}")
    ax.legend(loc="upper left")
    ax.grid(alpha=0.3)
    paths.append(_save(fig, out / FIGURES[3]))
    return paths


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path
