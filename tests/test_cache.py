"""The design cache (calib/cache.py): cold and warm give the same bytes, every input is in
the key, a broken entry is computed again, concurrent processes share it, and a cache that
cannot be written is no error."""

import dataclasses
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest

from calib import cache, dataset
from calib.ecu_params import build
from calib.fx_tables import build_tables
from calib.options import DesignOptions
from hil.config import default_vehicle
from hil.nodes import sil
from hil.sim.road import load_route

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    d = tmp_path / "cache"
    monkeypatch.setenv(cache.ENV_DIR, str(d))
    monkeypatch.delenv(cache.ENV_OFF, raising=False)
    monkeypatch.setenv(dataset.ENV_OFF, "1")    # (designed, not the committed calibration)
    return d


def entries(d: Path) -> list[Path]:
    return sorted(d.rglob("*.pickle"))


def trace_hash(params) -> str:
    rep, _ = sil.run(default_vehicle(), load_route("full_road_section"), "auto", 1,
                     params=params, duration_s=1.0, key=bytes(16))
    return rep["trace_sha256"]


def test_cold_and_warm_give_the_same_bytes(cache_dir, monkeypatch):
    cfg = default_vehicle()
    cold = build(cfg)
    (entry,) = entries(cache_dir)
    assert entry.parent.name == "ecu_params" and oct(cache_dir.stat().st_mode)[-3:] == "700"
    warm = build(cfg)
    assert warm is not cold                           # (read back from the disk)
    assert pickle.dumps(warm, 5) == pickle.dumps(cold, 5)
    monkeypatch.setenv(cache.ENV_OFF, "1")
    fresh = build(cfg)
    assert pickle.dumps(fresh, 5) == pickle.dumps(cold, 5)
    assert entries(cache_dir) == [entry]              # (off: nothing read or written)
    assert trace_hash(warm) == trace_hash(fresh)
    monkeypatch.delenv(cache.ENV_OFF)
    t_cold = build_tables(cold)
    assert pickle.dumps(build_tables(warm), 5) == pickle.dumps(t_cold, 5)
    assert len(entries(cache_dir)) == 2


def test_every_input_is_in_the_key(cache_dir):
    cfg = default_vehicle()
    base = build(cfg)
    stiffer = dataclasses.replace(cfg, vehicle=dataclasses.replace(
        cfg.vehicle, spring_stiffness_n_per_m=cfg.vehicle.spring_stiffness_n_per_m * 1.3))
    other = build(stiffer)           # (the same source file: the values make the key)
    assert not (other.control.k_safety == base.control.k_safety).all()
    opts = build(cfg, DesignOptions(ramp_s=0.1))
    assert opts.modes.ramp_ticks != base.modes.ramp_ticks
    assert len(entries(cache_dir)) == 3
    # the code's digest names its folder: another version of the design code reads none
    assert {p.parents[1].name for p in entries(cache_dir)} == {cache.code_digest()[:16]}


def test_a_broken_entry_is_computed_again(cache_dir):
    cfg = default_vehicle()
    good = pickle.dumps(build(cfg), 5)
    (entry,) = entries(cache_dir)
    entry.write_bytes(b"not a pickle")
    assert pickle.dumps(build(cfg), 5) == good
    assert entry.read_bytes() != b"not a pickle"


def test_an_unwritable_cache_warns_and_computes(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory would be")
    monkeypatch.setenv(cache.ENV_DIR, str(blocker / "cache"))
    monkeypatch.delenv(cache.ENV_OFF, raising=False)
    monkeypatch.setenv(dataset.ENV_OFF, "1")
    p = build(default_vehicle())
    assert p.dt_s > 0
    err = capsys.readouterr().err
    assert err.startswith("warning: design cache not written") and err.count("\n") == 1


def test_concurrent_processes_share_one_entry(cache_dir):
    """Two processes building the same calibration at once (two test workers, two campaign
    workers): both succeed, one entry, and it loads."""
    code = ("import hil, pickle, hashlib; from calib.ecu_params import build; "
            "from hil.config import default_vehicle; "
            "print(hashlib.sha256(pickle.dumps(build(default_vehicle()), 5)).hexdigest())")
    env = {**os.environ, cache.ENV_DIR: str(cache_dir)}
    procs = [subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    assert outs[0][0] == outs[1][0]
    (entry,) = entries(cache_dir)
    assert not list(entry.parent.glob(".tmp-*"))
    import hashlib

    assert hashlib.sha256(pickle.dumps(pickle.loads(entry.read_bytes()), 5)).hexdigest() \
        == outs[0][0].strip()


def test_hil_cache_command(cache_dir):
    build(default_vehicle())
    run = [sys.executable, "-m", "hil", "cache", "--json"]
    env = {**os.environ, cache.ENV_DIR: str(cache_dir)}
    import json

    got = json.loads(subprocess.run(run, cwd=ROOT, env=env, capture_output=True, text=True,
                                    check=True).stdout)
    assert got["entries"] == 1 and got["directory"] == str(cache_dir) and got["enabled"]
    got = json.loads(subprocess.run(run + ["--clear"], cwd=ROOT, env=env, capture_output=True,
                                    text=True, check=True).stdout)
    assert got["removed"] == 1 and got["entries"] == 0 and not entries(cache_dir)
