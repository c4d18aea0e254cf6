"""The report's figures (issue 20): the model's analytic PSD against its own variance, and
every figure written for a run."""

import numpy as np
import pytest

from calib.model import linear_model, output_covariance, passive_psd
from hil.config import load_vehicle


@pytest.mark.parametrize("gq, speed", [(6.4e-5, 20.0), (1.024e-3, 10.0)])
def test_the_analytic_psd_integrates_to_the_lyapunov_variance(gq, speed):
    """The PSD drawn over the Welch estimates is the model's: over frequency it integrates
    to the exact variance of each output (Parseval), within the quadrature's error."""
    model = linear_model(load_vehicle(None).vehicle, gq, speed)
    f = np.concatenate(([0.0], np.geomspace(1e-4, 2e3, 20000)))
    area = np.trapezoid(passive_psd(model, f), f, axis=1)
    var, _ = output_covariance(model)
    assert area == pytest.approx(var, rel=2e-3)


def test_every_figure_is_written(tmp_path):
    from hil.nodes import sil
    from hil.report.figures import FIGURES, write_outputs
    from hil.sim.road import load_route

    cfg, route = load_vehicle(None), load_route("city")
    report, trace = sil.run(cfg, route, "auto", 1, duration_s=8.0)
    paths = write_outputs(tmp_path, report, trace, cfg, route)
    names = [p.name for p in paths]
    assert names[:2] == ["report.json", "report.md"] and names[2:] == list(FIGURES)
    for p in paths[2:]:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000
    md = (tmp_path / "report.md").read_text()
    assert "negative" in md and all(f"![{f}]({f})" in md for f in FIGURES)


def test_progress_lines_without_a_terminal(tmp_path):
    """Without a terminal (a CI log, make run | tee) long work prints a line every 5 %."""
    import subprocess
    import sys
    from pathlib import Path

    proc = subprocess.run([sys.executable, "-m", "hil", "sim", "--route", "city", "--duration",
                           "4", "--mode", "comfort"], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [x for x in proc.stderr.splitlines() if x.startswith("SIL city (comfort): ")]
    pcts = [int(x.split(":")[1].split("%")[0]) for x in lines]
    assert pcts[0] == 0 and pcts[-1] == 100 and pcts == sorted(set(pcts))
    assert len(pcts) >= 10 and all(b - a <= 10 for a, b in zip(pcts, pcts[1:]))


@pytest.mark.parametrize("segments", [1, 5])
def test_every_title_lies_inside_its_figure(tmp_path, monkeypatch, segments):
    """A one-segment route cut the per-segment grids' titles at both ends (the figure 3.8 in
    wide for an 80-character title); every figure's title now lies inside it."""
    from hil.nodes import sil
    from hil.report import figures
    from hil.sim.road import load_route

    route = tmp_path / "r.toml"
    route.write_text('name = "a_route_with_a_long_enough_name"\n' + "".join(
        f'[[segment]]\ngrade = "{g}"\nlength_m = 120.0\nspeed_mps = 20.0\n'
        for g in "BCDCB"[:segments]))
    cfg, r = load_vehicle(None), load_route(str(route))
    report, trace = sil.run(cfg, r, "auto", 1)
    saved = figures._save
    inside = []

    def check(fig, path, **kw):
        fig.canvas.draw()
        box, title = fig.bbox, fig._suptitle.get_window_extent()
        inside.append((path.name, box.x0 <= title.x0 and title.x1 <= box.x1
                       and title.y1 <= box.y1))
        return saved(fig, path, **kw)

    monkeypatch.setattr(figures, "_save", check)
    figures.write_outputs(tmp_path, report, trace, cfg, r)
    assert len(inside) == len(figures.FIGURES) and all(ok for _, ok in inside), inside
