"""Report files of a SIL or HIL run: ``report.json``, ``report.md`` and PNG figures: per
segment, a window of BA, SWS and DTD against the passive twin (the paper's Figs. 13/15) and
their Welch PSDs with the passive model's exact PSD; BA and W_k-weighted BA RMS per segment;
grade, mode and an event timeline (faults, fail-safe, fallback, missed deadlines); the road
estimate against the truth; energy."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

from firmware.params import GRADE_NAMES, MODE_NAMES

FIGURES = ("timeseries.png", "psd.png", "comfort.png", "modes.png", "road.png", "energy.png")


# what the energy columns of a SIL or bench report mean (terminal table and report.md)
ENERGY_COLUMNS = ("Energy over the scored window: stored J into the storage element, drawn J "
                  "net from the supply (negative: energy returned to the supply through the "
                  "bridge).")


def _clean(value):
    from hil.cli import _clean as clean

    return clean(value)


def write_outputs(out: Path, report: dict, trace, cfg=None, route=None) -> list[Path]:
    """Write report.json, report.md and the figures into ``out``; returns the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    from hil.cli import write_atomic

    path = write_atomic(out / "report.json", json.dumps(_clean(report), indent=2) + "\n")
    figs = write_figures(out, report, trace, cfg, route)
    md = out / "report.md"
    md.write_text(markdown(report, [f.name for f in figs]))
    return [path, md, *figs]


def switches_phrase(report: dict) -> str:
    """"N mode switches for M grade changes", and ", the road-holding override K times" when
    it took over."""
    n = report.get("road_holding_entries", 0)
    held = f", the road-holding override {n} time{'s' if n != 1 else ''}" if n else ""
    return (f"{report['mode_switches']} mode switches for {report['grade_changes']} grade "
            f"changes{held}")


def _energy_line(energy: dict) -> str:
    if "stored_j" not in energy:     # a partial report whose plant wrote no record
        return "- energy: not recorded"
    return (f"- energy: harvested into storage {energy['stored_j']:.1f} J, drawn from the "
            f"supply {energy['supply_drawn_j']:.1f} J ({ENERGY_NOTE})")


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
              f"- grade accuracy {report['grade_accuracy']:.3f}; {switches_phrase(report)}",
              f"- driver: {report['driver']['policy']}, requests {report['driver']['requests']}",
              _energy_line(report["energy"]), ""]
    if "realtime" in bench:
        rt = bench["realtime"]
        lines += [f"- realtime: missed deadlines {rt['missed_deadlines']} "
                  f"({rt['missed_deadline_ratio']:.4f}), lag p50 {rt['lag_p50_us']:.0f} us, "
                  f"p99 {rt['lag_p99_us']:.0f} us, max {rt['lag_max_us']:.0f} us", ""]
    lines += ["Ratios are active / passive twin RMS on the same road, after "
              f"{report['settle_s']:g} s of each segment.", "",
              "| segment | BA | SWS | DTD | BA m/s² | SWS mm | DTD mm | grade ok | stored J "
              "| drawn J | road est. RMSE mm |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in report["segments"]:
        r, a = s["ratio"], s["active"]
        if not s.get("scored", True):
            lines.append(f"| {s['grade']}@{s['speed_mps']:g} m/s | {s['note']} |"
                         + " |" * 10)
            continue
        lines.append(
            f"| {s['grade']}@{s['speed_mps']:g} m/s | {r['ba']:.3f} | {r['sws']:.3f} | "
            f"{r['dtd']:.3f} | {a['ba_rms_mps2']:.3f} | {1e3 * a['sws_rms_m']:.2f} | "
            f"{1e3 * a['dtd_rms_m']:.2f} | {s['grade_accuracy']:.2f} | {s['harvested_j']:.1f} | "
            f"{s['consumed_j']:.1f} | {1e3 * s['road_estimate_rmse_m']:.1f} |")
    lines += ["", ENERGY_COLUMNS, ""] + _ride_lines(report)
    lines += ["Frames sent: " + ", ".join(
        f"{node} {sum(c.values())}" for node, c in report["frames_sent"].items()), ""]
    for f in figures:
        lines += [f"![{f}]({f})", ""]
    return "\n".join(lines)


def _ride_lines(report: dict) -> list[str]:
    """The ride verdict's rows (``report["ride"]``, hil.validate.ride) as a table."""
    rows = report.get("ride")
    if not rows:
        return []
    out = ["The ride: each scored segment against its mode's acceptance, each bound widened by "
           "the scatter its window adds over the designs' 180 s (`hil/validate/ride.py`).", "",
           "| segment | mode | ratio ≤ limit | worst | |", "|---|---|---|---|---|"]
    for r in rows:
        seg = f"{r['segment']}: {r['grade']}@{r['speed_mps']:g} m/s"
        if not r["judged"]:
            out.append(f"| {seg} | {r.get('mode', '–')} | {r['why']} | | |")
            continue
        bounds = ", ".join(f"{k} {b['got']:.3f} ≤ {b['limit']:.3f}"
                           for k, b in r["bounds"].items())
        out.append(f"| {seg} | {r['mode']} | {bounds} | {r['worst']:.3f} | "
                   f"{'pass' if r['ok'] else 'FAIL'} |")
    return out + [""]


def write_figures(out: Path, report: dict, trace, cfg=None, route=None) -> list[Path]:
    """The figures (``FIGURES``). ``cfg`` and ``route``: the vehicle and route of the run, for
    the model's analytic PSDs (left out without them)."""
    import matplotlib

    matplotlib.use("Agg")
    title = f"{report['route']}, mode {report['mode']}, seed {report['seed']}"
    segs = _segments(report, trace)
    return [_timeseries(out / FIGURES[0], trace, segs, title),
            _psd(out / FIGURES[1], trace, segs, title, cfg, route),
            _comfort(out / FIGURES[2], trace, segs, title),
            _modes(out / FIGURES[3], trace, title),
            _road(out / FIGURES[4], trace, title),
            _energy(out / FIGURES[5], trace, title)]


# ------------------------------------------------------------------ the figures
WINDOW_S = 2.0           # the per-segment time window (the paper's Figs. 13/15 show ~2 s)
MAX_COLUMNS = 8          # segments drawn side by side (a longer route: the first eight)
PASSIVE = dict(color="0.55", lw=0.9, label="passive")
ECU = dict(color="C0", lw=1.0, label="ECU")
# (in the time windows passive is drawn over the ECU's trace, dashed, so both show)
PASSIVE_OVER = dict(color="0.2", lw=0.7, ls=(0, (3, 2)), label="passive")
SIGNALS = (("ba", "BA (m/s²)", 1.0), ("sws", "SWS (mm)", 1e3), ("dtd", "DTD (mm)", 1e3))


def _segments(report: dict, trace) -> list[dict]:
    """The scored segments: index, label, the ticks after the settling time."""
    settle = int(round(report.get("settle_s", 3.0) / trace.dt_s))
    out = []
    for i, s in enumerate(report["segments"]):
        idx = np.flatnonzero(trace.segment == i)
        if not s.get("scored", True) or len(idx) <= settle:
            continue
        out.append({"i": i, "grade": s["grade"], "speed": s["speed_mps"],
                    "ticks": idx[settle:],
                    "label": f"{i + 1}: {s['grade']} @ {s['speed_mps']:g} m/s"})
    return out[:MAX_COLUMNS]


def _mode_in(trace, ticks) -> str:
    m = np.bincount(trace.arrays["mode"][ticks].astype(int), minlength=len(MODE_NAMES))
    return MODE_NAMES[int(np.argmax(m))]


def _timeseries(path: Path, trace, segs: list[dict], title: str) -> Path:
    """Per segment, a WINDOW_S window from the middle of its scored part: BA, SWS, DTD of the
    ECU's car against its passive twin (the paper's Figs. 13/15)."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    a, dt = trace.arrays, trace.dt_s
    n = max(1, len(segs))
    fig, axes = plt.subplots(3, n, figsize=(_grid_width(n), 6.8), squeeze=False,
                             sharey="row")
    w = int(round(WINDOW_S / dt))
    for j, seg in enumerate(segs):
        t = seg["ticks"]
        mid = t[len(t) // 2]
        win = np.arange(max(t[0], mid - w // 2), min(t[-1] + 1, mid - w // 2 + w))
        tw = win * dt
        for r, (key, label, scale) in enumerate(SIGNALS):
            ax = axes[r, j]
            ax.plot(tw, a[key][win] * scale, **ECU)
            ax.plot(tw, a[f"p_{key}"][win] * scale, **PASSIVE_OVER)
            ax.xaxis.set_major_locator(MaxNLocator(3))
            ax.grid(alpha=0.3)
            if j == 0:
                ax.set_ylabel(label)
        _column(axes, j, seg, _mode_in(trace, win), "t (s)")
    return _grid_done(fig, axes, path,
                      f"BA, SWS and DTD in a {WINDOW_S:g} s window of each segment: {title}")


def _psd(path: Path, trace, segs: list[dict], title: str, cfg, route) -> Path:
    """Welch PSDs of BA, SWS, DTD per segment, ECU and passive, with the passive model's
    analytic PSD (``calib.model.passive_psd``) where the vehicle and route are known."""
    import matplotlib.pyplot as plt
    from scipy.signal import welch

    a, fs = trace.arrays, 1.0 / trace.dt_s
    n = max(1, len(segs))
    fig, axes = plt.subplots(3, n, figsize=(_grid_width(n), 6.8), squeeze=False,
                             sharex=True)
    f_lo, f_hi = 0.25, min(50.0, fs / 2)         # (the band of the suspension's modes)
    f_model = np.geomspace(f_lo, f_hi, 300)
    for j, seg in enumerate(segs):
        t = seg["ticks"]
        nper = min(len(t), int(4.0 * fs))
        model = None
        if cfg is not None and route is not None:
            from calib.model import linear_model, passive_psd

            rs = route.segments[seg["i"]]
            model = passive_psd(linear_model(cfg.vehicle, rs.gq_m3, rs.speed_mps,
                                             route.road.convention,
                                             route.road.cutoff_n_per_m), f_model)
        for r, (key, label, scale) in enumerate(SIGNALS):
            ax = axes[r, j]
            for src, style in ((f"p_{key}", PASSIVE), (key, ECU)):
                f, pxx = welch(a[src][t] * scale, fs=fs, nperseg=nper)
                band = (f >= f_lo) & (f <= f_hi)
                ax.loglog(f[band], pxx[band], **style)
            if model is not None:
                ax.loglog(f_model, model[r] * scale ** 2, color="k", lw=0.8, ls="--",
                          label="passive, model (exact)")
            ax.set_xlim(f_lo, f_hi)
            ax.grid(alpha=0.3, which="both")
            if j == 0:
                unit = label.split("(")[1].rstrip(")")
                ax.set_ylabel(f"{label.split(' ')[0]} PSD (({unit})²/Hz)")
        _column(axes, j, seg, _mode_in(trace, t), "f (Hz)")
    return _grid_done(fig, axes, path,
                      f"Power spectral densities (Welch, 4 s segments) per segment: {title}")


def _column(axes, j: int, seg: dict, mode: str, xlabel: str) -> None:
    """A segment's column of a per-segment grid: its title (segment and mode) and x label."""
    axes[0, j].set_title(f"{seg['label']}\n{mode}", fontsize=9)
    axes[-1, j].set_xlabel(xlabel)


def _grid_width(n: int) -> float:
    """A per-segment grid's width (inches): 2.6 a segment, never narrower than its title
    needs on two lines (a one-segment route cut it at both ends)."""
    return max(2.6 * n + 1.2, 7.5)


def _grid_done(fig, axes, path: Path, suptitle: str) -> Path:
    import textwrap

    _legend(fig, axes[0, 0])
    # (the title wrapped to the figure: about 10 characters an inch at its size)
    text = textwrap.fill(suptitle, int(fig.get_figwidth() * 10))
    fig.suptitle(text, y=0.995)
    return _save(fig, path, top=0.86 - 0.03 * text.count("\n"))


def _comfort(path: Path, trace, segs: list[dict], title: str) -> Path:
    """Per segment: BA RMS and its ISO 2631-1 W_k-weighted RMS, passive and ECU."""
    import matplotlib.pyplot as plt

    from hil.sim.metrics import rms, wk_weighted_rms

    a, fs = trace.arrays, 1.0 / trace.dt_s
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    x = np.arange(len(segs))
    for ax, (name, fn) in zip(axes, (("BA RMS", rms),
                                     ("BA RMS, W_k-weighted (ISO 2631-1)",
                                      lambda v: wk_weighted_rms(v, fs)))):
        for k, (src, style, dx) in enumerate((("p_ba", PASSIVE, -0.2), ("ba", ECU, 0.2))):
            vals = [fn(a[src][s["ticks"]]) for s in segs]
            ax.bar(x + dx, vals, width=0.4, color=style["color"], label=style["label"])
        ax.set_xticks(x, [s["label"].split(": ")[1] for s in segs], rotation=30, ha="right",
                      fontsize=8)
        ax.set_ylabel("m/s²")
        ax.grid(alpha=0.3, axis="y")
        ax.set_title(name, fontsize=10)
    _legend(fig, axes[0], ncol=2)
    fig.suptitle(f"Ride comfort per segment (after the settling time): {title}", y=0.995)
    return _save(fig, path, top=0.80)


def _modes(path: Path, trace, title: str) -> Path:
    """Grade (true, estimated), mode (recommended, active), and a timeline of the ECU's faults,
    its fail-safe, the plant's passive fallback and (realtime) missed deadlines."""
    import matplotlib.pyplot as plt

    from firmware import safety

    a, dt = trace.arrays, trace.dt_s
    n = len(trace.segment)
    t = np.arange(n) * dt
    fig, ax = plt.subplots(3, 1, figsize=(11, 7), sharex=True,
                           gridspec_kw={"height_ratios": [1, 1, 1.2]})
    ge = a["grade_est"].astype(float)
    ge[ge > 3] = np.nan
    ax[0].step(t, trace.true_grade, where="post", color="k", label="true")
    ax[0].step(t, ge, where="post", color="C1", label="estimated")
    ax[0].set_yticks(range(4), list(GRADE_NAMES))
    ax[0].set_ylabel("grade")
    ax[1].step(t, a["recommended"], where="post", color="C2", label="recommended")
    ax[1].step(t, a["mode"], where="post", color="C3", label="active")
    ax[1].set_yticks(range(len(MODE_NAMES)), list(MODE_NAMES))
    rows = []
    faults = a["faults"].astype(np.int64)
    for bit, name in sorted(safety.FAULT_NAMES.items()):
        on = (faults & bit) != 0
        if on.any():
            rows.append((f"fault: {name}", on, "C3"))
    rows.append(("fail-safe", (faults & safety.SAFETY_RELEVANT) != 0, "C1"))
    rows.append(("plant fallback", a["fallback"] > 0, "C4"))
    if "missed" in a:
        rows.append(("missed deadline", a["missed"].astype(bool), "C5"))
    least = n * dt / 400                 # (a one-tick event still shows)
    for r, (name, on, color) in enumerate(rows):
        for s0, s1 in _runs(on):
            ax[2].add_patch(plt.Rectangle((s0 * dt, r - 0.35), max((s1 - s0) * dt, least),
                                          0.7, color=color, lw=0))
    ax[2].set_yticks(range(len(rows)), [r[0] for r in rows], fontsize=8)
    ax[2].set_ylim(-0.6, len(rows) - 0.4)
    ax[2].set_xlim(0, n * dt)
    ax[2].set_xlabel("t (s)")
    ax[2].set_title("events: a row per fault seen; fail-safe and plant fallback (a late or "
                    "missing command) always listed", fontsize=9, loc="left")
    for x in ax:
        x.grid(alpha=0.3)
    for x in ax[:2]:
        x.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, frameon=False)
    fig.suptitle(f"Grade, mode and events: {title}", y=0.995)
    return _save(fig, path, right=0.87)


def _runs(on: np.ndarray) -> list[tuple[int, int]]:
    """The [start, end) tick ranges where ``on`` holds."""
    d = np.diff(np.concatenate(([0], on.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def _road(path: Path, trace, title: str) -> Path:
    import matplotlib.pyplot as plt

    a, dt = trace.arrays, trace.dt_s
    n = len(trace.segment)
    fig, ax = plt.subplots(2, 1, figsize=(11, 5))
    mid = n // 2
    w = slice(max(0, mid - int(2.5 / dt)), min(n, mid + int(2.5 / dt)))
    tw = np.arange(n)[w] * dt
    ax[0].plot(tw, a["zf"][w] * 1e3, color="k", lw=0.8, label="true road")
    ax[0].plot(tw, a["road_est"][w] * 1e3, color="C0", lw=0.8, label="AKF estimate")
    ax[0].set_ylabel("road (mm)")
    ax[1].plot(tw, a["dtd"][w] * 1e3, color="k", lw=0.8, label="true DTD")
    ax[1].plot(tw, a["dtd_est"][w] * 1e3, color="C1", lw=0.8, label="estimated DTD")
    ax[1].set_ylabel("DTD (mm)")
    ax[1].set_xlabel("t (s)")
    for x in ax:
        x.grid(alpha=0.3)
        x.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, frameon=False)
    fig.suptitle(f"Road and tyre-deflection estimates against the truth (5 s): {title}",
                 y=0.995)
    return _save(fig, path, right=0.85)


ENERGY_NOTE = ("Harvested: into the storage element while the bridge regenerates. "
               "Drawn: taken by the bridge from the vehicle's supply; it falls (goes "
               "negative) while the motor, driven by the road, pushes current back into "
               "the supply.")


def _energy(path: Path, trace, title: str) -> Path:
    import matplotlib.pyplot as plt

    a, dt = trace.arrays, trace.dt_s
    n = len(trace.segment)
    t = np.arange(n) * dt
    fig, ax = plt.subplots(figsize=(11, 4))
    ax.plot(t, a["stored"], color="C2", label="harvested into storage")
    ax.plot(t, a["drawn"], color="C3", label="drawn from the supply")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_ylabel("energy since the start (J)")
    ax.set_xlabel("t (s)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8, frameon=False)
    fig.suptitle(f"Energy: {title}", y=0.995)
    fig.text(0.01, 0.01, ENERGY_NOTE, fontsize=8, color="0.3", wrap=True)
    return _save(fig, path, right=0.82, bottom=0.2)


def _legend(fig, ax, ncol: int = 3) -> None:
    """One legend for the figure, above the axes (never over data)."""
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.955),
               ncol=ncol, frameon=False, fontsize=9)


def _save(fig, path: Path, top: float = 0.93, right: float = 0.98,
          bottom: Optional[float] = None) -> Path:
    fig.tight_layout()
    fig.subplots_adjust(top=top, right=right, **({"bottom": bottom} if bottom else {}))
    fig.savefig(path, dpi=90, metadata={"Software": None})
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path
