"""GA-LQR tuning (tools.tune_ga_lqr) and the gains file the ECU loads."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calib.control_design import default_gains_path, load_gains
from calib.galqr import tune
from calib.linear import RelativeFamily, physical_limits
from calib.model import linear_model
from calib.options import DesignOptions
from hil.config import ConfigError, default_vehicle, load_vehicle
from hil.sim.road import gq_of

ROOT = Path(__file__).resolve().parents[1]
CFG = default_vehicle()


def test_ga_finds_a_feasible_near_optimal_point_deterministically():
    a = tune(CFG, seed=3)
    b = tune(CFG, seed=3)
    assert a["K"] == b["K"] and a["feasible"]
    bound = np.array(DesignOptions().comprehensive_bound)
    r = np.array([a["ratios"][k] for k in ("ba", "sws", "dtd")])
    assert np.all(r <= bound + 1e-9)
    limit = physical_limits(linear_model(CFG.vehicle, gq_of("D"), 20.0))["eq43"].value
    assert a["fitness"] >= limit - 1e-9          # never beats the physical limit
    # and a brute-force sample of the same LQR family does no better than the GA
    fam = RelativeFamily(linear_model(CFG.vehicle, gq_of("D"), 20.0))
    rng = np.random.default_rng(0)
    best = np.inf
    for _ in range(300):
        _, rr = fam.evaluate(10.0 ** rng.uniform(-3, 5, 3))
        if np.all(rr <= bound):
            best = min(best, rr.sum())
    assert a["fitness"] <= best + 1e-3


def test_shipped_gains_file_matches_a_fresh_tuning():
    shipped = json.loads(default_gains_path(CFG).read_text())
    fresh = tune(CFG, seed=shipped["seed"])
    assert np.allclose(shipped["K"], fresh["K"], rtol=1e-9)


def test_cli_writes_the_gains_file_and_json(tmp_path):
    out = tmp_path / "g.json"
    proc = subprocess.run([sys.executable, "-m", "tools.tune_ga_lqr", "--vehicle",
                           str(ROOT / "hil/vehicles/suv.toml"), "--seed", "2", "--out", str(out),
                           "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    o = json.loads(proc.stdout)
    assert {"q", "K", "fitness"} <= o.keys() and len(o["K"]) == 5 and len(o["q"]) == 3
    suv = load_vehicle(ROOT / "hil/vehicles/suv.toml")
    assert np.allclose(load_gains(out, suv), o["K"])
    with pytest.raises(ConfigError, match="another vehicle"):
        load_gains(out, CFG)


def test_bad_gains_files(tmp_path):
    for text, word in (("{", "invalid JSON"), ('{"K": [1, 2]}', "'K'"),
                       ('{"K": [1, 2, 3, 4, "x"]}', "'K'"), ('[1]', "'K'")):
        p = tmp_path / "g.json"
        p.write_text(text)
        with pytest.raises(ConfigError, match=word):
            load_gains(p, CFG)
    with pytest.raises(ConfigError, match="cannot read"):
        load_gains(tmp_path / "missing.json", CFG)


def test_the_ga_draws_from_its_own_generator_not_the_process_wide_one():
    """Another thread drawing from ``random`` while the GA runs (a Dask worker's event loop
    does) changes nothing: the same gains as alone, and the global generator is not reseeded."""
    import random
    import threading

    from calib.galqr import tune
    from hil.config import load_vehicle

    cfg = load_vehicle(Path(__file__).resolve().parents[1] / "hil" / "vehicles" / "suv.toml")
    alone = tune(cfg, 0, population=12, generations=4)["K"]
    stop = threading.Event()

    def draw():
        while not stop.is_set():
            random.random()

    t = threading.Thread(target=draw)
    t.start()
    try:
        busy = tune(cfg, 0, population=12, generations=4)["K"]
    finally:
        stop.set()
        t.join()
    assert busy == alone
    random.seed(123)
    before = random.random()
    random.seed(123)
    tune(cfg, 0, population=4, generations=1)
    assert random.random() == before


def test_the_bound_follows_the_vehicle():
    """Eq. (44)'s bound is each ratio's own: at most the cap and exp(-z sigma) over a drive of
    ``ratio_window_s`` at the tuned gain, and no tighter. The SUV with its spring x0.7, whose
    Eq. (43) optimum has BA and DTD above 0.95, then comes within 0.03 of its limit, where a
    fixed 0.95 for every ratio leaves it further away."""
    import dataclasses

    from calib.galqr import WINDOW_TOL
    from calib.model import output_covariance, window_scatter

    suv = load_vehicle(ROOT / "hil/vehicles/suv.toml")
    v = suv.vehicle
    soft = dataclasses.replace(suv, vehicle=dataclasses.replace(
        v, spring_stiffness_n_per_m=0.7 * v.spring_stiffness_n_per_m))
    model = linear_model(soft.vehicle, gq_of("D"), 20.0)
    limit = physical_limits(model)["eq43"].value
    opts = DesignOptions()
    a = tune(soft)
    assert a["feasible"]
    K = np.array(a["K"])
    _, sigma = window_scatter(model, K, opts.ratio_window_s)
    top = np.minimum(opts.comprehensive_bound, np.exp(-opts.ratio_window_z * sigma))
    r = np.sqrt(output_covariance(model, K)[0] / output_covariance(model)[0])
    assert np.all(r <= top + WINDOW_TOL), (r, top)
    assert np.allclose(a["window_bound"], top)
    assert r.sum() - limit <= 0.03, (r.sum(), limit)
    fixed = np.array(tune(soft, bound=(0.95, 0.95, 0.95))["K"])
    r_fixed = np.sqrt(output_covariance(model, fixed)[0] / output_covariance(model)[0])
    assert r_fixed.sum() - limit > r.sum() - limit + 0.03
